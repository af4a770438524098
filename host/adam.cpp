// AdamW step on flat arrays, global gradient L2 norm and norm clipping.
#include "host/adam.hpp"

#include <cmath>

#include "core/eigen.hpp"
#include "core/error.hpp"

namespace pillarseg::host {

namespace {

template <class T>
using FlatArray = Eigen::Array<T, Eigen::Dynamic, 1>;

template <class T>
Eigen::Map<FlatArray<T>> flat(std::span<T> values) {
  return {values.data(), static_cast<Eigen::Index>(values.size())};
}

template <class T>
Eigen::Map<const FlatArray<T>> flat(std::span<const T> values) {
  return {values.data(), static_cast<Eigen::Index>(values.size())};
}

}  // namespace

template <class T>
void adam_step(std::span<T> params, std::span<const T> grads, std::span<T> exp_avg,
               std::span<T> exp_avg_sq, int64_t step, const AdamOptions& options) {
  const char* op = "adam_step";
  PS_CHECK(grads.size() == params.size() && exp_avg.size() == params.size() &&
               exp_avg_sq.size() == params.size(),
           "{}: expected params, grads, exp_avg, exp_avg_sq of one length, given {}, {}, {}, {}",
           op, params.size(), grads.size(), exp_avg.size(), exp_avg_sq.size());
  PS_CHECK(step >= 1, "{}: expected step >= 1 (1-based, counting this step), given {}", op, step);
  PS_CHECK(options.lr >= 0 && options.eps >= 0 && options.weight_decay >= 0,
           "{}: expected lr, eps, weight_decay >= 0, given {}, {}, {}", op, options.lr, options.eps,
           options.weight_decay);
  PS_CHECK(options.beta1 >= 0 && options.beta1 < 1 && options.beta2 >= 0 && options.beta2 < 1,
           "{}: expected beta1, beta2 in [0, 1), given {}, {}", op, options.beta1, options.beta2);

  auto p = flat(params);
  const auto g = flat(grads);
  auto m = flat(exp_avg);
  auto v = flat(exp_avg_sq);
  const double bias_correction1 = 1 - std::pow(options.beta1, static_cast<double>(step));
  const double bias_correction2 = 1 - std::pow(options.beta2, static_cast<double>(step));

  p *= static_cast<T>(1 - options.lr * options.weight_decay);
  m = static_cast<T>(options.beta1) * m + static_cast<T>(1 - options.beta1) * g;
  v = static_cast<T>(options.beta2) * v + static_cast<T>(1 - options.beta2) * g.square();
  // PyTorch's arrangement of lr * mhat / (sqrt(vhat) + eps).
  const auto step_size = static_cast<T>(options.lr / bias_correction1);
  const auto inv_sqrt_bias_correction2 = static_cast<T>(1 / std::sqrt(bias_correction2));
  p -= step_size * m / (v.sqrt() * inv_sqrt_bias_correction2 + static_cast<T>(options.eps));
}

template <class T>
double grad_norm(std::span<const std::span<T>> grads) {
  double sum_squares = 0;
  for (const std::span<T>& g : grads) {
    sum_squares += flat(std::span<const T>(g)).template cast<double>().square().sum();
  }
  return std::sqrt(sum_squares);
}

template <class T>
double clip_grad_norm(std::span<const std::span<T>> grads, double max_norm) {
  PS_CHECK(max_norm > 0, "clip_grad_norm: expected max_norm > 0, given {}", max_norm);
  const double norm = grad_norm(grads);
  const double coefficient = clip_coefficient(norm, max_norm);
  if (coefficient < 1) {
    for (const std::span<T>& g : grads) flat(g) *= static_cast<T>(coefficient);
  }
  return norm;
}

double clip_coefficient(double norm, double max_norm) {
  const double coefficient = max_norm / (norm + 1e-6);
  return coefficient < 1 ? coefficient : 1.0;
}

template void adam_step<float>(std::span<float>, std::span<const float>, std::span<float>,
                               std::span<float>, int64_t, const AdamOptions&);
template void adam_step<double>(std::span<double>, std::span<const double>, std::span<double>,
                                std::span<double>, int64_t, const AdamOptions&);
template double grad_norm<float>(std::span<const std::span<float>>);
template double grad_norm<double>(std::span<const std::span<double>>);
template double clip_grad_norm<float>(std::span<const std::span<float>>, double);
template double clip_grad_norm<double>(std::span<const std::span<double>>, double);

}  // namespace pillarseg::host
