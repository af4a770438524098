// AdamW step on flat arrays, global gradient L2 norm and norm clipping.
#include "host/adam.hpp"

#include <cmath>
#include <cstdint>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/parallel.hpp"

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

  const double bias_correction1 = 1 - std::pow(options.beta1, static_cast<double>(step));
  const double bias_correction2 = 1 - std::pow(options.beta2, static_cast<double>(step));
  const auto decay = static_cast<T>(1 - options.lr * options.weight_decay);
  const auto beta1 = static_cast<T>(options.beta1);
  const auto one_minus_beta1 = static_cast<T>(1 - options.beta1);
  const auto beta2 = static_cast<T>(options.beta2);
  const auto one_minus_beta2 = static_cast<T>(1 - options.beta2);
  // PyTorch's arrangement of lr * mhat / (sqrt(vhat) + eps).
  const auto step_size = static_cast<T>(options.lr / bias_correction1);
  const auto inv_sqrt_bias_correction2 = static_cast<T>(1 / std::sqrt(bias_correction2));
  const auto eps = static_cast<T>(options.eps);
  const auto update = [&](size_t begin, size_t end) {
    auto p = flat(params.subspan(begin, end - begin));
    const auto g = flat(grads.subspan(begin, end - begin));
    auto m = flat(exp_avg.subspan(begin, end - begin));
    auto v = flat(exp_avg_sq.subspan(begin, end - begin));
    p *= decay;
    m = beta1 * m + one_minus_beta1 * g;
    v = beta2 * v + one_minus_beta2 * g.square();
    p -= step_size * m / (v.sqrt() * inv_sqrt_bias_correction2 + eps);
  };
  // Every element's update is its own, but Eigen computes the elements before a destination's
  // first aligned packet and after its last whole one without vectors (where the compiler may
  // contract a multiply-add differently): the threads' ranges start and end at addresses aligned
  // for the widest packet in all three destinations, so that each element takes the path it
  // takes in one pass. Where the three are not aligned alike, one pass.
  constexpr size_t kAlign = 64;
  const auto phase = [](const T* x) { return reinterpret_cast<std::uintptr_t>(x) % kAlign; };
  const size_t n = params.size();
  const std::uintptr_t misalignment = phase(params.data());
  const int threads = num_threads();
  if (threads < 2 || n < 4 * kAlign || misalignment % sizeof(T) != 0 ||
      phase(exp_avg.data()) != misalignment || phase(exp_avg_sq.data()) != misalignment) {
    update(0, n);
    return;
  }
  const size_t head = (kAlign - misalignment) % kAlign / sizeof(T);  // elements before alignment
  const size_t unit = kAlign / sizeof(T);
  const size_t units = (n - head) / unit;
  parallel_chunks(threads, [&](int64_t t0, int64_t t1, int) {
    for (int64_t t = t0; t < t1; ++t) {
      const size_t begin = t == 0 ? 0 : head + units * static_cast<size_t>(t) / threads * unit;
      const size_t end =
          t + 1 == threads ? n : head + units * static_cast<size_t>(t + 1) / threads * unit;
      if (begin < end) update(begin, end);
    }
  });
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
