// Channel softmax (B, K, H, W) -> (B, K, H, W) and arg-max class ids (B, K, H, W) -> (B, H, W),
// of any values or of the largest positive one.
#include "host/softmax.hpp"

#include <cmath>

#include "core/eigen.hpp"

namespace pillarseg::host {

namespace {

template <class T>
using Plane = Eigen::Array<T, Eigen::Dynamic, 1>;

void check_logits(const char* op, const Shape& shape) {
  PS_CHECK(shape.size() == 4 && shape[1] > 0,
           "{}: expected logits of shape (B, K, H, W) with K > 0, given {}", op, shape_str(shape));
}

}  // namespace

template <class T>
void softmax_channels(const Tensor<T>& logits, Tensor<T>& probabilities) {
  const char* op = "softmax_channels";
  check_logits(op, logits.shape());
  PS_CHECK(&probabilities != &logits, "{}: probabilities must not be the logits (not in place)",
           op);
  const int64_t batch = logits.dim(0), classes = logits.dim(1);
  const int64_t plane = logits.dim(2) * logits.dim(3);
  probabilities.resize(logits.shape());
  Plane<T> max_logit(plane);
  Plane<T> sum(plane);
  for (int64_t b = 0; b < batch; ++b) {
    auto z = [&](int64_t k) {
      return Eigen::Map<const Plane<T>>(logits.data() + (b * classes + k) * plane, plane);
    };
    auto p = [&](int64_t k) {
      return Eigen::Map<Plane<T>>(probabilities.data() + (b * classes + k) * plane, plane);
    };
    max_logit = z(0);
    for (int64_t k = 1; k < classes; ++k) max_logit = max_logit.max(z(k));
    sum.setZero();
    for (int64_t k = 0; k < classes; ++k) {
      p(k) = (z(k) - max_logit).exp();
      sum += p(k);
    }
    const Plane<T> inv_sum = sum.inverse();
    for (int64_t k = 0; k < classes; ++k) p(k) *= inv_sum;
  }
}

namespace {

// Per cell, 1 + the channel of the best value over the K channels (a channel wins where
// `better(value, best so far)`): from channel 0's value, or, with `from_zero`, from 0 with class 0.
template <class T, class Better>
void best_class_ids(const char* op, const Tensor<T>& values, bool from_zero, Better better,
                    Tensor<uint8_t>& class_ids) {
  check_logits(op, values.shape());
  const int64_t batch = values.dim(0), classes = values.dim(1);
  const int64_t height = values.dim(2), width = values.dim(3);
  PS_CHECK(classes <= 255, "{}: expected at most 255 channels for uint8 class ids, given {}", op,
           classes);
  const int64_t plane = height * width;
  class_ids.resize({batch, height, width});
  Plane<T> best(plane);
  for (int64_t b = 0; b < batch; ++b) {
    const T* z = values.data() + b * classes * plane;
    uint8_t* ids = class_ids.data() + b * plane;
    for (int64_t i = 0; i < plane; ++i) {
      best[i] = from_zero ? T(0) : z[i];
      ids[i] = from_zero ? 0 : 1;
    }
    for (int64_t k = from_zero ? 0 : 1; k < classes; ++k) {
      const T* zk = z + k * plane;
      for (int64_t i = 0; i < plane; ++i) {
        if (better(zk[i], best[i])) {
          best[i] = zk[i];
          ids[i] = static_cast<uint8_t>(k + 1);
        }
      }
    }
  }
}

}  // namespace

template <class T>
void argmax_class_ids(const Tensor<T>& logits, Tensor<uint8_t>& class_ids) {
  best_class_ids("argmax_class_ids", logits, /*from_zero=*/false,
                 [](T v, T best) { return v > best || (std::isnan(v) && !std::isnan(best)); }, class_ids);
}

template <class T>
void argmax_positive_class_ids(const Tensor<T>& values, Tensor<uint8_t>& class_ids) {
  best_class_ids("argmax_positive_class_ids", values, /*from_zero=*/true, [](T v, T best) { return v > best; },
                 class_ids);
}

template void softmax_channels<float>(const Tensor<float>&, Tensor<float>&);
template void softmax_channels<double>(const Tensor<double>&, Tensor<double>&);
template void argmax_class_ids<float>(const Tensor<float>&, Tensor<uint8_t>&);
template void argmax_class_ids<double>(const Tensor<double>&, Tensor<uint8_t>&);
template void argmax_positive_class_ids<float>(const Tensor<float>&, Tensor<uint8_t>&);
template void argmax_positive_class_ids<double>(const Tensor<double>&, Tensor<uint8_t>&);

}  // namespace pillarseg::host
