#include "host/confusion.hpp"

#include "core/classes.hpp"
#include "core/error.hpp"

namespace pillarseg::host {

void confusion_accumulate(const Tensor<uint8_t>& truth, const Tensor<uint8_t>& predicted, const Tensor<uint8_t>* mask,
                          Tensor<int64_t>& confusion) {
  PS_CHECK(truth.shape() == predicted.shape(), "confusion: truth {} and prediction {} differ in shape",
           shape_str(truth.shape()), shape_str(predicted.shape()));
  PS_CHECK(!mask || mask->shape() == truth.shape(), "confusion: mask {} and truth {} differ in shape",
           shape_str(mask->shape()), shape_str(truth.shape()));
  PS_CHECK(confusion.shape() == (Shape{kNumClasses, kNumClasses}), "confusion: matrix must be (12, 12), got {}",
           shape_str(confusion.shape()));
  for (int64_t i = 0; i < truth.numel(); ++i) {
    const int t = truth[i], p = predicted[i];
    if (t == 0 || (mask && (*mask)[i] == 0)) continue;
    PS_CHECK(t <= kNumClasses, "confusion: true class id {} at cell {} is outside 0..12", t, i);
    PS_CHECK(p >= 1 && p <= kNumClasses, "confusion: predicted class id {} at cell {} is outside 1..12", p, i);
    confusion(t - 1, p - 1) += 1;
  }
}

}  // namespace pillarseg::host
