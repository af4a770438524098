// PointPillars PFN layer: Linear (no bias) -> BatchNorm1d -> ReLU -> max over the N slots of each
// pillar; (P, N, D) -> (P, C). Training and evaluation forward, training backward.
#include "host/pfn.hpp"

#include <cmath>

#include "core/eigen.hpp"

namespace pillarseg::host {

namespace {

template <class T>
using RowMatrix = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

struct PfnShape {
  int64_t pillars = 0;   // P
  int64_t slots = 0;     // N
  int64_t features = 0;  // D
  int64_t channels = 0;  // C
  int64_t rows() const { return pillars * slots; }
};

template <class T>
PfnShape check_input_and_weight(const char* op, const Tensor<T>& input, const Tensor<T>& weight) {
  PS_CHECK(input.rank() == 3 && input.dim(1) > 0 && input.dim(2) > 0,
           "{}: expected input of shape (P, N, D) with N, D > 0, given {}", op,
           shape_str(input.shape()));
  PS_CHECK(weight.rank() == 2 && weight.dim(1) == input.dim(2),
           "{}: expected weight of shape (C, {}) for input of shape {}, given {}", op, input.dim(2),
           shape_str(input.shape()), shape_str(weight.shape()));
  return {input.dim(0), input.dim(1), input.dim(2), weight.dim(0)};
}

// z = input . weight^T, (P * N, C).
template <class T>
void linear(const Tensor<T>& input, const Tensor<T>& weight, const PfnShape& s, Tensor<T>& z) {
  z.resize({s.rows(), s.channels});
  const Eigen::Map<const RowMatrix<T>> points(input.data(), s.rows(), s.features);
  const Eigen::Map<const RowMatrix<T>> w(weight.data(), s.channels, s.features);
  Eigen::Map<RowMatrix<T>>(z.data(), s.rows(), s.channels).noalias() = points * w.transpose();
}

// out(p, c) = max over n of activations(p * N + n, c), NaN winning as in torch.max.
// max_slot(p, c) = the first n reaching it, or -1 where the max is not > 0 (see PfnSaved).
template <class T>
void max_over_slots(const Tensor<T>& activations, const PfnShape& s, Tensor<T>& out,
                    Tensor<int32_t>& max_slot) {
  out.resize({s.pillars, s.channels});
  max_slot.resize({s.pillars, s.channels});
  for (int64_t p = 0; p < s.pillars; ++p) {
    const T* pillar = activations.data() + p * s.slots * s.channels;
    T* best = out.data() + p * s.channels;
    int32_t* best_slot = max_slot.data() + p * s.channels;
    for (int64_t c = 0; c < s.channels; ++c) best[c] = pillar[c];
    for (int64_t n = 1; n < s.slots; ++n) {
      const T* row = pillar + n * s.channels;
      for (int64_t c = 0; c < s.channels; ++c) {
        if (row[c] > best[c] || (std::isnan(row[c]) && !std::isnan(best[c]))) {
          best[c] = row[c];
          best_slot[c] = static_cast<int32_t>(n);
        }
      }
    }
    for (int64_t c = 0; c < s.channels; ++c) {
      if (!(best[c] > T(0))) best_slot[c] = -1;
    }
  }
}

}  // namespace

template <class T>
void pfn_forward_train(const Tensor<T>& input, const Tensor<T>& weight, const Tensor<T>& gamma,
                       const Tensor<T>& beta, const BatchNormOptions& options,
                       Tensor<T>& running_mean, Tensor<T>& running_var,
                       int64_t& num_batches_tracked, Tensor<T>& out, PfnSaved<T>& saved,
                       T* scratch) {
  const PfnShape s = check_input_and_weight("pfn_forward_train", input, weight);
  // z, then BatchNorm + ReLU in place
  Tensor<T> activations = scratch ? Tensor<T>::view(scratch, {s.rows(), s.channels}) : Tensor<T>();
  linear(input, weight, s, activations);
  batchnorm_relu_forward_train(activations, gamma, beta, options, running_mean, running_var,
                               num_batches_tracked, activations, saved.norm);
  max_over_slots(activations, s, out, saved.max_slot);
}

template <class T>
void pfn_forward_eval(const Tensor<T>& input, const Tensor<T>& weight, const Tensor<T>& gamma,
                      const Tensor<T>& beta, const Tensor<T>& running_mean,
                      const Tensor<T>& running_var, const BatchNormOptions& options,
                      Tensor<T>& out) {
  const PfnShape s = check_input_and_weight("pfn_forward_eval", input, weight);
  Tensor<T> activations;  // z, then BatchNorm + ReLU in place
  linear(input, weight, s, activations);
  batchnorm_relu_forward_eval(activations, gamma, beta, running_mean, running_var, options,
                              activations);
  Tensor<int32_t> max_slot;
  max_over_slots(activations, s, out, max_slot);
}

template <class T>
void pfn_backward(const Tensor<T>& d_out, const Tensor<T>& input, const Tensor<T>& weight,
                  const Tensor<T>& gamma, const PfnSaved<T>& saved, Tensor<T>& d_input,
                  Tensor<T>& d_weight, Tensor<T>& d_gamma, Tensor<T>& d_beta, T* scratch,
                  ReplicaSum* replicas) {
  const char* op = "pfn_backward";
  const PfnShape s = check_input_and_weight(op, input, weight);
  const Shape out_shape{s.pillars, s.channels};
  PS_CHECK(d_out.shape() == out_shape, "{}: expected d_out of shape {}, given {}", op,
           shape_str(out_shape), shape_str(d_out.shape()));
  PS_CHECK(saved.max_slot.shape() == out_shape,
           "{}: expected saved.max_slot of shape {} (from pfn_forward_train), given {}", op,
           shape_str(out_shape), shape_str(saved.max_slot.shape()));

  // The max and the ReLU route d_out(p, c) to one row of dL/d(BatchNorm output), or nowhere.
  // BatchNorm's backward then turns it into dL/dz in place.
  const Shape rows_shape{s.rows(), s.channels};
  Tensor<T> dz = scratch ? Tensor<T>::view(scratch, rows_shape) : Tensor<T>();
  dz.resize(rows_shape);  // zero
  for (int64_t p = 0; p < s.pillars; ++p) {
    for (int64_t c = 0; c < s.channels; ++c) {
      const int32_t slot = saved.max_slot(p, c);
      PS_CHECK(slot >= -1 && slot < s.slots,
               "{}: saved.max_slot({}, {}) = {} is neither -1 nor a slot of N = {}", op, p, c, slot,
               s.slots);
      if (slot >= 0) dz(p * s.slots + slot, c) = d_out(p, c);
    }
  }

  Tensor<T> z =
      scratch ? Tensor<T>::view(scratch + s.rows() * s.channels, rows_shape) : Tensor<T>();
  linear(input, weight, s, z);
  batchnorm_backward(dz, z, gamma, saved.norm, dz, d_gamma, d_beta, replicas);

  const Eigen::Map<const RowMatrix<T>> points(input.data(), s.rows(), s.features);
  const Eigen::Map<const RowMatrix<T>> w(weight.data(), s.channels, s.features);
  const Eigen::Map<const RowMatrix<T>> dz_m(dz.data(), s.rows(), s.channels);
  d_input.resize(input.shape());
  Eigen::Map<RowMatrix<T>>(d_input.data(), s.rows(), s.features).noalias() = dz_m * w;
  d_weight.resize(weight.shape());
  Eigen::Map<RowMatrix<T>>(d_weight.data(), s.channels, s.features).noalias() =
      dz_m.transpose() * points;
}

#define PILLARSEG_INSTANTIATE_PFN(T)                                                          \
  template void pfn_forward_train<T>(const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,    \
                                     const Tensor<T>&, const BatchNormOptions&, Tensor<T>&,   \
                                     Tensor<T>&, int64_t&, Tensor<T>&, PfnSaved<T>&, T*);     \
  template void pfn_forward_eval<T>(const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,     \
                                    const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,     \
                                    const BatchNormOptions&, Tensor<T>&);                     \
  template void pfn_backward<T>(const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,         \
                                const Tensor<T>&, const PfnSaved<T>&, Tensor<T>&, Tensor<T>&, \
                                Tensor<T>&, Tensor<T>&, T*, ReplicaSum*);

PILLARSEG_INSTANTIATE_PFN(float)
PILLARSEG_INSTANTIATE_PFN(double)

}  // namespace pillarseg::host
