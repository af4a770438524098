// Weighted softmax cross-entropy, one-hot sigmoid BCE and the Lovász-softmax loss over the
// labelled cells of logits (B, K, H, W) with labels (B, H, W); each returns the loss and writes
// d_logits.
#include "host/losses.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

#include "core/eigen.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {

namespace {

template <class T>
using Plane = Eigen::Array<T, Eigen::Dynamic, 1>;

// Checks the shapes and the labels; returns M, the number of labelled cells.
template <class T>
int64_t check_and_count_labelled(const char* op, const Tensor<T>& logits,
                                 const Tensor<uint8_t>& labels, const Tensor<T>* d_logits) {
  PS_CHECK(logits.rank() == 4 && logits.dim(1) > 0,
           "{}: expected logits of shape (B, K, H, W) with K > 0, given {}", op,
           shape_str(logits.shape()));
  const int64_t classes = logits.dim(1), height = logits.dim(2), width = logits.dim(3);
  const Shape label_shape{logits.dim(0), height, width};
  PS_CHECK(labels.shape() == label_shape,
           "{}: expected labels of shape {} for logits of shape {}, given {}", op,
           shape_str(label_shape), shape_str(logits.shape()), shape_str(labels.shape()));
  PS_CHECK(d_logits != &logits, "{}: d_logits must not be the logits (not in place)", op);
  int64_t labelled = 0;
  for (int64_t i = 0; i < labels.numel(); ++i) {
    PS_CHECK(labels[i] <= classes,
             "{}: label {} at (batch {}, iy {}, ix {}) is not a class id in 0..{}", op, labels[i],
             i / (height * width), i / width % height, i % width, classes);
    labelled += labels[i] != 0;
  }
  return labelled;
}

// The cross-entropy's and BCE's class weights: one per class id 0..K, finite and >= 0.
void check_class_weights(const char* op, int64_t classes, std::span<const double> class_weights) {
  PS_CHECK(static_cast<int64_t>(class_weights.size()) == classes + 1,
           "{}: expected {} class weights (one per class id 0..{}), given {}", op, classes + 1,
           classes, class_weights.size());
  for (int64_t k = 1; k <= classes; ++k) {
    PS_CHECK(std::isfinite(class_weights[k]) && class_weights[k] >= 0,
             "{}: expected finite class weights >= 0, given {} for class {}", op, class_weights[k],
             k);
  }
}

}  // namespace

template <class T>
double cross_entropy_loss(const Tensor<T>& logits, const Tensor<uint8_t>& labels,
                          std::span<const double> class_weights,
                          std::type_identity_t<Tensor<T>>* d_logits) {
  const int64_t labelled = check_and_count_labelled("cross_entropy_loss", logits, labels, d_logits);
  check_class_weights("cross_entropy_loss", logits.dim(1), class_weights);
  if (labelled == 0) {
    if (d_logits) d_logits->resize(logits.shape());  // all zero
    return 0.0;
  }
  if (d_logits) d_logits->resize_for_overwrite(logits.shape());  // every element written below

  const int64_t batch = logits.dim(0), classes = logits.dim(1);
  const int64_t plane = logits.dim(2) * logits.dim(3);
  const double inv_labelled = 1.0 / static_cast<double>(labelled);
  const auto z = [&](int64_t b, int64_t k) {
    return Eigen::Map<const Plane<T>>(logits.data() + (b * classes + k) * plane, plane);
  };
  // Per image (in parallel: each image's planes whole on one thread), log sum_k exp(z_k) per cell.
  std::vector<Plane<T>> log_sum_exp(static_cast<size_t>(batch));
  parallel_for(batch, [&](int64_t b) {
    Plane<T> max_logit = z(b, 0);
    for (int64_t k = 1; k < classes; ++k) max_logit = max_logit.max(z(b, k));
    Plane<T> sum_exp = Plane<T>::Zero(plane);
    for (int64_t k = 0; k < classes; ++k) sum_exp += (z(b, k) - max_logit).exp();
    log_sum_exp[static_cast<size_t>(b)] = max_logit + sum_exp.log();
  });
  // The loss over the labelled cells in the order (b, cell): one sum, as one thread adds it.
  std::vector<Plane<T>> cell_weight(static_cast<size_t>(batch));  // c[y] / M in labelled cells
  double loss = 0;
  for (int64_t b = 0; b < batch; ++b) {
    const T* zb = logits.data() + b * classes * plane;
    const uint8_t* y = labels.data() + b * plane;
    Plane<T>& weight = cell_weight[static_cast<size_t>(b)];
    weight.resize(plane);
    for (int64_t i = 0; i < plane; ++i) {
      const int label = y[i];
      if (label == 0) continue;
      const double true_logit = zb[(label - 1) * plane + i];
      loss += class_weights[label] *
              (static_cast<double>(log_sum_exp[static_cast<size_t>(b)][i]) - true_logit);
      weight[i] = static_cast<T>(class_weights[label] * inv_labelled);
    }
  }
  if (!d_logits) return loss * inv_labelled;
  // d_k = c[y] / M * (softmax_k - [k == y - 1]) in labelled cells, 0 elsewhere (even for NaN
  // logits there), plane by plane in parallel. The exponentials are vectorised over the plane;
  // the per-cell choice is a plain loop (Eigen 3.4 does not vectorise select()).
  parallel_for(batch * classes, [&](int64_t bk) {
    const int64_t b = bk / classes, k = bk % classes;
    const uint8_t* y = labels.data() + b * plane;
    const Plane<T>& weight = cell_weight[static_cast<size_t>(b)];
    T* d = d_logits->data() + bk * plane;
    Eigen::Map<Plane<T>>(d, plane) = (z(b, k) - log_sum_exp[static_cast<size_t>(b)]).exp();
    for (int64_t i = 0; i < plane; ++i) {
      d[i] = y[i] == 0 ? T(0) : weight[i] * (d[i] - T(y[i] == k + 1));
    }
  });
  return loss * inv_labelled;
}

template <class T>
double bce_loss(const Tensor<T>& logits, const Tensor<uint8_t>& labels,
                std::span<const double> class_weights, std::type_identity_t<Tensor<T>>* d_logits) {
  const int64_t labelled = check_and_count_labelled("bce_loss", logits, labels, d_logits);
  check_class_weights("bce_loss", logits.dim(1), class_weights);
  if (d_logits) d_logits->resize(logits.shape());
  if (labelled == 0) return 0.0;

  const int64_t batch = logits.dim(0), classes = logits.dim(1);
  const int64_t plane = logits.dim(2) * logits.dim(3);
  const double inv_pairs = 1.0 / static_cast<double>(labelled * classes);
  Plane<T> exp_minus_abs(plane);  // exp(-|z|) in (0, 1]: neither softplus nor sigmoid overflows
  Plane<T> log1p_exp_minus_abs(plane);
  double loss = 0;
  for (int64_t b = 0; b < batch; ++b) {
    const uint8_t* y = labels.data() + b * plane;
    for (int64_t k = 0; k < classes; ++k) {
      const T* z = logits.data() + (b * classes + k) * plane;
      const Eigen::Map<const Plane<T>> z_plane(z, plane);
      exp_minus_abs = (-z_plane.abs()).exp();
      log1p_exp_minus_abs = exp_minus_abs.log1p();
      // Per cell: softplus(x) = max(x, 0) + log(1 + exp(-|x|)); the loss is softplus(-z) for
      // the positive channel (k == y - 1) and softplus(z) for the others. The gradient is
      // sigmoid(z) - [positive], sigmoid(z) = 1 / (1 + exp(-z)) for z >= 0 and
      // exp(z) / (1 + exp(z)) for z < 0.
      const auto positive_class = static_cast<uint8_t>(k + 1);
      const auto gradient_scale = static_cast<T>(class_weights[k + 1] * inv_pairs);
      T* d = d_logits ? d_logits->data() + (b * classes + k) * plane : nullptr;
      double channel_loss = 0;
      for (int64_t i = 0; i < plane; ++i) {
        if (y[i] == 0) {
          if (d) d[i] = T(0);
          continue;
        }
        const bool positive = y[i] == positive_class;
        const T signed_z = positive ? -z[i] : z[i];
        channel_loss += std::max(signed_z, T(0)) + log1p_exp_minus_abs[i];
        if (d) {
          const T sigmoid = (z[i] >= T(0) ? T(1) : exp_minus_abs[i]) / (T(1) + exp_minus_abs[i]);
          d[i] = gradient_scale * (sigmoid - T(positive));
        }
      }
      loss += class_weights[k + 1] * channel_loss;
    }
  }
  return loss * inv_pairs;
}

template <class T>
double lovasz_softmax_loss(const Tensor<T>& logits, const Tensor<uint8_t>& labels,
                           std::type_identity_t<Tensor<T>>* d_logits) {
  const int64_t labelled = check_and_count_labelled("lovasz_softmax_loss", logits, labels, d_logits);
  if (d_logits) {
    d_logits->resize(logits.shape());
    std::fill(d_logits->data(), d_logits->data() + d_logits->numel(), T(0));
  }
  if (labelled == 0) return 0.0;

  const int64_t batch = logits.dim(0), classes = logits.dim(1);
  const int64_t plane = logits.dim(2) * logits.dim(3);
  // The softmax of each labelled cell, cell-major: probs[m * K + k].
  std::vector<T> probs(static_cast<size_t>(labelled * classes));
  std::vector<uint8_t> cell_label(static_cast<size_t>(labelled));
  std::vector<int64_t> cell_offset(static_cast<size_t>(labelled));  // b * K * plane + i
  int64_t m = 0;
  for (int64_t b = 0; b < batch; ++b) {
    const T* zb = logits.data() + b * classes * plane;
    const uint8_t* y = labels.data() + b * plane;
    for (int64_t i = 0; i < plane; ++i) {
      if (y[i] == 0) continue;
      T* p = probs.data() + m * classes;
      T max_logit = zb[i];
      for (int64_t k = 1; k < classes; ++k) max_logit = std::max(max_logit, zb[k * plane + i]);
      T sum = 0;
      for (int64_t k = 0; k < classes; ++k) sum += p[k] = std::exp(zb[k * plane + i] - max_logit);
      for (int64_t k = 0; k < classes; ++k) p[k] /= sum;
      cell_label[m] = y[i];
      cell_offset[m] = b * classes * plane + i;
      ++m;
    }
  }

  // step[c][bin]: the Jaccard step over the bin shared by its cells; present: classes in labels.
  std::vector<std::array<int64_t, 2>> counts(kLovaszBins);  // [background, foreground]
  std::vector<double> step(static_cast<size_t>(classes * kLovaszBins));
  std::vector<int64_t> foreground(static_cast<size_t>(classes + 1), 0);
  for (int64_t j = 0; j < labelled; ++j) ++foreground[cell_label[j]];
  int present = 0;
  double loss = 0;
  for (int64_t k = 0; k < classes; ++k) {
    const int64_t total_fg = foreground[k + 1];
    if (total_fg == 0) continue;
    ++present;
    std::fill(counts.begin(), counts.end(), std::array<int64_t, 2>{0, 0});
    for (int64_t j = 0; j < labelled; ++j) {
      const bool fg = cell_label[j] == k + 1;
      const T p = probs[j * classes + k];
      ++counts[lovasz_bin(fg ? T(1) - p : p)][fg];
    }
    double* class_step = step.data() + k * kLovaszBins;
    int64_t ranked_fg = 0, ranked_bg = 0;  // the cells of the bins ranked before this one
    for (int bin = kLovaszBins - 1; bin >= 0; --bin) {
      const int64_t n = counts[bin][0] + counts[bin][1];
      if (n == 0) continue;
      const double before = lovasz_jaccard(total_fg, ranked_fg, ranked_bg);
      ranked_fg += counts[bin][1];
      ranked_bg += counts[bin][0];
      class_step[bin] =
          (lovasz_jaccard(total_fg, ranked_fg, ranked_bg) - before) / static_cast<double>(n);
    }
    for (int64_t j = 0; j < labelled; ++j) {
      const bool fg = cell_label[j] == k + 1;
      const T p = probs[j * classes + k];
      const T error = fg ? T(1) - p : p;
      loss += static_cast<double>(error) * class_step[lovasz_bin(error)];
    }
  }
  if (d_logits) {
    // d/dz_k of (1 / C) sum_c s_c p_c, s_c = +-step (error = p or 1 - p): p_k (s_k - sum_c s_c p_c).
    const double inv_present = 1.0 / present;
    std::vector<double> s(static_cast<size_t>(classes));
    for (int64_t j = 0; j < labelled; ++j) {
      const T* p = probs.data() + j * classes;
      double weighted = 0;
      for (int64_t k = 0; k < classes; ++k) {
        s[k] = 0;
        if (foreground[k + 1] == 0) continue;
        const bool fg = cell_label[j] == k + 1;
        const T error = fg ? T(1) - p[k] : p[k];
        s[k] = (fg ? -inv_present : inv_present) * step[k * kLovaszBins + lovasz_bin(error)];
        weighted += s[k] * p[k];
      }
      T* d = d_logits->data() + cell_offset[j];
      for (int64_t k = 0; k < classes; ++k) d[k * plane] = static_cast<T>(p[k] * (s[k] - weighted));
    }
  }
  return loss / present;
}

template double cross_entropy_loss<float>(const Tensor<float>&, const Tensor<uint8_t>&,
                                          std::span<const double>, Tensor<float>*);
template double cross_entropy_loss<double>(const Tensor<double>&, const Tensor<uint8_t>&,
                                           std::span<const double>, Tensor<double>*);
template double bce_loss<float>(const Tensor<float>&, const Tensor<uint8_t>&,
                                std::span<const double>, Tensor<float>*);
template double bce_loss<double>(const Tensor<double>&, const Tensor<uint8_t>&,
                                 std::span<const double>, Tensor<double>*);
template double lovasz_softmax_loss<float>(const Tensor<float>&, const Tensor<uint8_t>&,
                                           Tensor<float>*);
template double lovasz_softmax_loss<double>(const Tensor<double>&, const Tensor<uint8_t>&,
                                            Tensor<double>*);

}  // namespace pillarseg::host
