// TimedBackend: a Backend that forwards every call to another and adds its wall time (and, for
// the convolutions and the PFN, its FLOPs) to a total per op: where a model step's time goes.
#pragma once

#include <fmt/format.h>

#include <map>
#include <memory>
#include <string>
#include <type_traits>

#include "bench/support/step_timing.hpp"
#include "engine/model/backend.hpp"

namespace pillarseg::bench {

struct OpTotal {
  double seconds = 0.0, flops = 0.0;
  int64_t calls = 0;
};

// Forwards every Backend call to `inner` and adds its wall time (and, for the convolutions, its
// multiply-add count x 2) to a total per op. The CPU backend is synchronous, so a call's wall
// time is the op's time.
class TimedBackend final : public Backend {
 public:
  explicit TimedBackend(std::unique_ptr<Backend> inner) : inner_(std::move(inner)) {}

  const std::map<std::string, OpTotal>& totals() const { return totals_; }
  void clear_totals() { totals_.clear(); }

  Device device() const override { return inner_->device(); }
  std::string name() const override { return "timed " + inner_->name(); }
  void* allocate(size_t bytes) override { return inner_->allocate(bytes); }
  void deallocate(void* p) noexcept override { inner_->deallocate(p); }
  void upload(void* dst, const void* src, size_t bytes) override {
    timed("memory: upload, fill", 0, [&] { inner_->upload(dst, src, bytes); });
  }
  void download(void* dst, const void* src, size_t bytes) override {
    timed("memory: upload, fill", 0, [&] { inner_->download(dst, src, bytes); });
  }
  void fill_zero(void* dst, size_t bytes) override {
    timed("memory: upload, fill", 0, [&] { inner_->fill_zero(dst, bytes); });
  }

  void make_current() override { inner_->make_current(); }
  Counters counters() const override { return inner_->counters(); }

  void pad_points(const IRef& num_points, Ref& points) override {
    timed("input: points, pillars", 0, [&] { inner_->pad_points(num_points, points); });
  }
  int64_t pillar_gather(const Ref& points, const GridSpec& grid, int max_pillars, IRef& cell,
                        IRef& point_index, IRef& count, IRef& num_pillars) override {
    return timed("input: points, pillars", 0, [&] {
      return inner_->pillar_gather(points, grid, max_pillars, cell, point_index, count,
                                   num_pillars);
    });
  }
  void decorate_points(const Ref& points, const GridSpec& grid, const IRef& cell,
                       const IRef& point_index, const IRef& count, Ref& out) override {
    timed("input: points, pillars", 0,
          [&] { inner_->decorate_points(points, grid, cell, point_index, count, out); });
  }
  void batch_cells(const IRef& cell, int sample, IRef& cells) override {
    timed("input: points, pillars", 0, [&] { inner_->batch_cells(cell, sample, cells); });
  }
  void observability_2d(const Ref& points, const Eigen::Vector3d& origin, const GridSpec& grid,
                        URef& transmissions, URef& detections) override {
    timed("input: ray walks, maps", 0, [&] {
      inner_->observability_2d(points, origin, grid, transmissions, detections);
    });
  }
  void observability_input(const URef& transmissions, const URef& detections, Ref& out) override {
    timed("input: ray walks, maps", 0,
          [&] { inner_->observability_input(transmissions, detections, out); });
  }
  void occupancy_3d(const Ref& points, const Eigen::Vector3d& origin, const GridSpec& grid,
                    Ref& probability) override {
    timed("input: ray walks, maps", 0,
          [&] { inner_->occupancy_3d(points, origin, grid, probability); });
  }
  void grid_map_features(const Ref& points, const GridSpec& grid, const URef& detections,
                         const URef& transmissions, Ref& out) override {
    timed("input: ray walks, maps", 0,
          [&] { inner_->grid_map_features(points, grid, detections, transmissions, out); });
  }
  void mask_unobserved(const URef& transmissions, const URef& detections, LRef& labels,
                       Ref* probabilities) override {
    timed("softmax, argmax", 0,
          [&] { inner_->mask_unobserved(transmissions, detections, labels, probabilities); });
  }

  void pfn_forward(const Ref& points, const Ref& weight, BatchNormRefs& bn, bool training,
                   IRef& argmax, Ref& out, const Ref& scratch) override {
    timed("pfn forward", linear_flops(points, weight),
          [&] { inner_->pfn_forward(points, weight, bn, training, argmax, out, scratch); });
  }
  void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn,
                    const IRef& argmax, const Ref& dout, Ref& d_points, Ref& dweight, Ref& dgamma,
                    Ref& dbeta, const Ref& scratch) override {
    timed("pfn backward", 2 * linear_flops(points, weight), [&] {
      inner_->pfn_backward(points, weight, bn, argmax, dout, d_points, dweight, dgamma, dbeta,
                           scratch);
    });
  }
  void scatter_forward(const Ref& features, const IRef& cells, int channel0, Ref& canvas) override {
    timed("scatter forward", 0,
          [&] { inner_->scatter_forward(features, cells, channel0, canvas); });
  }
  void scatter_backward(const Ref& dcanvas, const IRef& cells, int channel0,
                        Ref& dfeatures) override {
    timed("scatter backward", 0,
          [&] { inner_->scatter_backward(dcanvas, cells, channel0, dfeatures); });
  }
  void copy_channels(const Ref& x, int channel0, Ref& y) override {
    timed("channel copies", 0, [&] { inner_->copy_channels(x, channel0, y); });
  }
  void extract_channels(const Ref& y, int channel0, Ref& x) override {
    timed("channel copies", 0, [&] { inner_->extract_channels(y, channel0, x); });
  }

  void conv2d_forward(const Ref& x, const Ref& w, const Ref* bias, int pad, Ref& y) override {
    timed(conv_op(w, "forward"), conv_flops(y, w),
          [&] { inner_->conv2d_forward(x, w, bias, pad, y); });
  }
  void conv2d_bn_relu_eval(const Ref& x, const Ref& w, const Ref* bias, const BatchNormRefs& bn,
                           int pad, Ref& y) override {
    timed(conv_op(w, "+BN+ReLU eval"), conv_flops(y, w),
          [&] { inner_->conv2d_bn_relu_eval(x, w, bias, bn, pad, y); });
  }
  bool supports_precision(Precision p, std::string* why_not) const override {
    return inner_->supports_precision(p, why_not);
  }
  void prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn, Precision p, HRef& w16,
                            Ref& bias_out) override {
    timed("16-bit weights", 0, [&] { inner_->prepare_conv_weights(w, bias, bn, p, w16, bias_out); });
  }
  void prepare_conv_transpose_weights(const Ref& w, const Ref* bias, Precision p, HRef& w16, Ref& bias_out) override {
    timed("16-bit weights", 0, [&] { inner_->prepare_conv_transpose_weights(w, bias, p, w16, bias_out); });
  }
  void conv2d_half_forward(const ActRef& x, const HRef& w16, const Ref& bias_out, const Shape& weight, int pad,
                           bool relu, Precision p, const ActRef& y) override {
    const double flops = 2.0 * static_cast<double>(y.numel()) * static_cast<double>(weight[1] * weight[2] * weight[3]);
    timed(fmt::format("conv{}x{} {} (tensor cores)", weight[2], weight[3], precision_name(p)), flops,
          [&] { inner_->conv2d_half_forward(x, w16, bias_out, weight, pad, relu, p, y); });
  }
  void conv_transpose2x2_half_forward(const ActRef& x, const HRef& w16, const Ref& bias_out, const Shape& weight,
                                      Precision p, const ActRef& y) override {
    const double flops = 2.0 * static_cast<double>(x.numel()) * static_cast<double>(weight[1] * 4);
    timed(fmt::format("convT 2x2 {} (tensor cores)", precision_name(p)), flops,
          [&] { inner_->conv_transpose2x2_half_forward(x, w16, bias_out, weight, p, y); });
  }
  void to_half(const Ref& x, Precision p, HRef& y) override {
    timed("16-bit activations", 0, [&] { inner_->to_half(x, p, y); });
  }
  void maxpool2x2_half(const HRef& x, Precision p, HRef& y) override {
    timed("16-bit activations", 0, [&] { inner_->maxpool2x2_half(x, p, y); });
  }
  void upsample2x_half(const HRef& x, Precision p, HRef& y) override {
    timed("16-bit activations", 0, [&] { inner_->upsample2x_half(x, p, y); });
  }
  void pad_concat_half(const HRef& skip, const HRef& up, HRef& y) override {
    timed("16-bit activations", 0, [&] { inner_->pad_concat_half(skip, up, y); });
  }
  void copy_channels_half(const HRef& x, int channel0, HRef& y) override {
    timed("16-bit activations", 0, [&] { inner_->copy_channels_half(x, channel0, y); });
  }
  void conv2d_backward(const Ref& x, const Ref& w, const Ref& dy, int pad, Ref* dx, Ref& dw,
                       Ref* dbias) override {
    const double passes = dx != nullptr ? 2.0 : 1.0;  // dw, and dx when asked for
    timed(conv_op(w, "backward"), passes * conv_flops(dy, w),
          [&] { inner_->conv2d_backward(x, w, dy, pad, dx, dw, dbias); });
  }
  bool supports_training_precision(Precision p, std::string* why_not) const override {
    return inner_->supports_training_precision(p, why_not);
  }
  void begin_sum_over_replicas(Ref& values, Replicas& replicas) override {
    inner_->begin_sum_over_replicas(values, replicas);
  }
  void end_sums_over_replicas(Replicas& replicas) override { inner_->end_sums_over_replicas(replicas); }
  bool supports_synchronized_batchnorm(std::string* why_not) const override {
    return inner_->supports_synchronized_batchnorm(why_not);
  }
  void conv2d_backward_half(const Ref& x, const Ref& w, const Ref& dy, int pad, Precision p, Ref* dx, Ref& dw,
                            Ref* dbias) override {
    const double passes = dx != nullptr ? 2.0 : 1.0;
    timed(fmt::format("conv{}x{} backward {} (tensor cores)", w.dim(2), w.dim(3), precision_name(p)),
          passes * conv_flops(dy, w), [&] { inner_->conv2d_backward_half(x, w, dy, pad, p, dx, dw, dbias); });
  }
  void conv_transpose2x2_backward_half(const Ref& x, const Ref& w, const Ref& dy, Precision p, Ref& dx, Ref& dw,
                                       Ref* dbias) override {
    timed(fmt::format("convT 2x2 backward {} (tensor cores)", precision_name(p)), 2 * transposed_flops(x, w),
          [&] { inner_->conv_transpose2x2_backward_half(x, w, dy, p, dx, dw, dbias); });
  }
  void conv_transpose2d_forward(const Ref& x, const Ref& w, const Ref* bias, Ref& y) override {
    timed("convT 2x2 forward", transposed_flops(x, w),
          [&] { inner_->conv_transpose2d_forward(x, w, bias, y); });
  }
  void conv_transpose2d_backward(const Ref& x, const Ref& w, const Ref& dy, Ref& dx, Ref& dw,
                                 Ref* dbias) override {
    timed("convT 2x2 backward", 2 * transposed_flops(x, w),
          [&] { inner_->conv_transpose2d_backward(x, w, dy, dx, dw, dbias); });
  }
  void batchnorm_relu_forward(const Ref& x, BatchNormRefs& bn, bool training, Ref& y) override {
    timed("batchnorm+relu forward", 0, [&] { inner_->batchnorm_relu_forward(x, bn, training, y); });
  }
  void batchnorm_relu_backward(const Ref& x, const Ref& y, const Ref& dy, const BatchNormRefs& bn,
                               Ref& dx, Ref& dgamma, Ref& dbeta) override {
    timed("batchnorm+relu backward", 0,
          [&] { inner_->batchnorm_relu_backward(x, y, dy, bn, dx, dgamma, dbeta); });
  }
  void maxpool2x2_forward(const Ref& x, Ref& y, IRef& argmax) override {
    timed("maxpool forward", 0, [&] { inner_->maxpool2x2_forward(x, y, argmax); });
  }
  void maxpool2x2_backward(const Ref& dy, const IRef& argmax, Ref& dx) override {
    timed("maxpool backward", 0, [&] { inner_->maxpool2x2_backward(dy, argmax, dx); });
  }
  void upsample2x_forward(const Ref& x, Ref& y) override {
    timed("upsample forward", 0, [&] { inner_->upsample2x_forward(x, y); });
  }
  void upsample2x_backward(const Ref& dy, Ref& dx) override {
    timed("upsample backward", 0, [&] { inner_->upsample2x_backward(dy, dx); });
  }
  void pad_concat_forward(const Ref& skip, const Ref& up, Ref& y) override {
    timed("pad+concat forward", 0, [&] { inner_->pad_concat_forward(skip, up, y); });
  }
  void pad_concat_backward(const Ref& dy, Ref& dskip, Ref& dup) override {
    timed("pad+concat backward", 0, [&] { inner_->pad_concat_backward(dy, dskip, dup); });
  }
  void add_inplace(Ref& a, const Ref& b) override {
    timed("add (skip gradients)", 0, [&] { inner_->add_inplace(a, b); });
  }
  void softmax(const Ref& logits, Ref& probs) override {
    timed("softmax, argmax", 0, [&] { inner_->softmax(logits, probs); });
  }
  void argmax(const Ref& logits, LRef& labels) override {
    timed("softmax, argmax", 0, [&] { inner_->argmax(logits, labels); });
  }
  double loss(LossKind kind, const Ref& logits, const LRef& labels, const Ref& coefficients,
              Ref& dlogits) override {
    return timed("loss", 0,
                 [&] { return inner_->loss(kind, logits, labels, coefficients, dlogits); });
  }
  double sum_of_squares(const Ref& x) override {
    return timed("optimizer: norm, clip, adam", 0, [&] { return inner_->sum_of_squares(x); });
  }
  void scale(Ref& x, float factor) override {
    timed("optimizer: norm, clip, adam", 0, [&] { inner_->scale(x, factor); });
  }
  void adam_step(Ref& param, const Ref& grad, Ref& m, Ref& v, int64_t step, const AdamOptions& options) override {
    timed("optimizer: norm, clip, adam", 0, [&] { inner_->adam_step(param, grad, m, v, step, options); });
  }

 private:
  template <class Fn>
  std::invoke_result_t<Fn&> timed(const std::string& op, double flops, Fn&& fn) {
    const Clock::time_point start = Clock::now();
    const auto add = [&] {
      OpTotal& t = totals_[op];
      t.seconds += std::chrono::duration<double>(Clock::now() - start).count();
      t.flops += flops;
      ++t.calls;
    };
    if constexpr (std::is_void_v<std::invoke_result_t<Fn&>>) {
      fn();
      add();
    } else {
      auto result = fn();
      add();
      return result;
    }
  }
  static std::string conv_op(const Ref& w, const char* pass) {
    return fmt::format("conv{}x{} {}", w.dim(2), w.dim(3), pass);
  }
  // y (B, O, h, w), weight (O, I, k, k).
  static double conv_flops(const Ref& y, const Ref& w) {
    return 2.0 * static_cast<double>(y.numel()) *
           static_cast<double>(w.dim(1) * w.dim(2) * w.dim(3));
  }
  // x (B, I, h, w), weight (I, O, 2, 2).
  static double transposed_flops(const Ref& x, const Ref& w) {
    return 2.0 * static_cast<double>(x.numel()) *
           static_cast<double>(w.dim(1) * w.dim(2) * w.dim(3));
  }
  // points (P, N, 10), weight (C, 10).
  static double linear_flops(const Ref& points, const Ref& w) {
    return 2.0 * static_cast<double>(points.numel()) * static_cast<double>(w.dim(0));
  }

  std::unique_ptr<Backend> inner_;
  std::map<std::string, OpTotal> totals_;
};

}  // namespace pillarseg::bench
