// host/ softmax, arg-max class ids and the two segmentation losses: hand-computed values on a
// two-cell example, invariants (sums to 1, unlabeled cells inert, shift invariance), gradients
// against central finite differences in double, stability for large logits, argument errors.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "host/losses.hpp"
#include "host/softmax.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::dot;
using pillarseg::test::numeric_gradient;
using pillarseg::test::random_tensor;
using namespace pillarseg::host;
using ::testing::HasSubstr;

namespace {

constexpr int64_t kClasses = 12;
// The sparse-ground-truth coefficients: vehicle 2, person / two-wheel / rider 8, others 1.
const std::vector<double> kWeights = {0, 2, 8, 8, 8, 1, 1, 1, 1, 1, 1, 1, 1};
const double kNaN = std::numeric_limits<double>::quiet_NaN();

Tensor<uint8_t> random_labels(const Shape& shape, Rng& rng) {
  Tensor<uint8_t> labels(shape);
  for (int64_t i = 0; i < labels.numel(); ++i) {
    labels[i] = static_cast<uint8_t>(rng.uniform_int(kClasses + 1));
  }
  return labels;
}

std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

using LossFn = double (*)(const TensorD&, const Tensor<uint8_t>&, std::span<const double>,
                          TensorD*);
struct NamedLoss {
  const char* name;
  LossFn loss;
};
const std::array<NamedLoss, 2> kLosses = {NamedLoss{"cross_entropy", &cross_entropy_loss<double>},
                                          NamedLoss{"bce", &bce_loss<double>}};

// The two-cell example plus one unlabeled cell, (B, K, H, W) = (1, 12, 1, 3):
//   cell 0: label 1 (weight 2), all logits 0;
//   cell 1: label 5 (weight 1), logit ln 11 in channel 4 (class 5), 0 elsewhere;
//   cell 2: unlabeled, NaN and huge logits that must not matter.
struct TwoCells {
  TensorD logits{Shape{1, kClasses, 1, 3}};
  Tensor<uint8_t> labels{Shape{1, 1, 3}};
  TwoCells() {
    labels[0] = 1, labels[1] = 5, labels[2] = 0;
    logits(0, 4, 0, 1) = std::log(11.0);
    for (int64_t k = 0; k < kClasses; ++k) logits(0, k, 0, 2) = k % 2 ? kNaN : 1e30;
  }
};

}  // namespace

// ---------------------------------------------------------------- softmax and arg-max

TEST(HostSoftmax, SumsToOneAndMatchesTheDefinition) {
  Rng rng(1);
  const TensorD logits = random_tensor({2, kClasses, 5, 3}, rng, -4, 4);
  TensorD p;
  softmax_channels(logits, p);
  ASSERT_EQ(p.shape(), logits.shape());
  TensorD expected(logits.shape());
  for (int64_t b = 0; b < 2; ++b) {
    for (int64_t y = 0; y < 5; ++y) {
      for (int64_t x = 0; x < 3; ++x) {
        double sum = 0, sum_p = 0;
        for (int64_t k = 0; k < kClasses; ++k) sum += std::exp(logits(b, k, y, x));
        for (int64_t k = 0; k < kClasses; ++k) {
          expected(b, k, y, x) = std::exp(logits(b, k, y, x)) / sum;
          sum_p += p(b, k, y, x);
        }
        EXPECT_NEAR(sum_p, 1.0, 1e-14);
      }
    }
  }
  EXPECT_TRUE(test::all_close(p, expected, 1e-15, 1e-13));

  TensorF p_float;
  softmax_channels(tensor_cast<float>(logits), p_float);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(p_float), expected, 1e-7, 1e-6));
}

TEST(HostSoftmax, StableForLargeLogitsAndShiftInvariant) {
  TensorF logits({1, 3, 1, 2});
  logits(0, 0, 0, 0) = 1000, logits(0, 1, 0, 0) = 999, logits(0, 2, 0, 0) = -1000;
  logits(0, 0, 0, 1) = -1000, logits(0, 1, 0, 1) = -1000, logits(0, 2, 0, 1) = -1000;
  TensorF p;
  softmax_channels(logits, p);
  const double e = std::exp(-1.0);
  EXPECT_NEAR(p(0, 0, 0, 0), 1 / (1 + e), 1e-6);
  EXPECT_NEAR(p(0, 1, 0, 0), e / (1 + e), 1e-6);
  EXPECT_EQ(p(0, 2, 0, 0), 0.0f);
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(p(0, k, 0, 1), 1.0 / 3, 1e-6);

  Rng rng(2);
  const TensorD z = random_tensor({2, kClasses, 5, 3}, rng, -3, 3);
  TensorD shifted = z;
  for (int64_t i = 0; i < shifted.numel(); ++i) shifted[i] += 500;
  TensorD p1, p2;
  softmax_channels(z, p1);
  softmax_channels(shifted, p2);
  EXPECT_TRUE(test::all_close(p2, p1, 1e-12, 1e-10));
}

TEST(HostSoftmax, NaNLogitMakesItsCellNaN) {
  TensorD logits({1, 4, 1, 2}, 0.5);
  logits(0, 2, 0, 1) = kNaN;
  TensorD p;
  softmax_channels(logits, p);
  for (int k = 0; k < 4; ++k) {
    EXPECT_DOUBLE_EQ(p(0, k, 0, 0), 0.25);
    EXPECT_TRUE(std::isnan(p(0, k, 0, 1))) << "channel " << k;
  }
}

TEST(HostArgmax, ClassIsChannelPlusOneAndTiesGoLow) {
  TensorD logits({1, kClasses, 1, 5}, 0.0);
  // cell 0: all equal -> class 1; cell 1: channels 3 and 7 tie at the max -> class 4;
  // cell 2: the last channel -> class 12; cell 3: NaN in channel 5 wins, as torch.argmax;
  // cell 4: -inf everywhere but channel 2.
  logits(0, 3, 0, 1) = logits(0, 7, 0, 1) = 2.5;
  logits(0, 11, 0, 2) = 1e-12;
  logits(0, 5, 0, 3) = kNaN;
  logits(0, 0, 0, 3) = 9;
  for (int64_t k = 0; k < kClasses; ++k) {
    logits(0, k, 0, 4) = k == 2 ? -1e30 : -std::numeric_limits<double>::infinity();
  }
  Tensor<uint8_t> ids;
  argmax_class_ids(logits, ids);
  ASSERT_EQ(ids.shape(), (Shape{1, 1, 5}));
  EXPECT_EQ(ids[0], 1);
  EXPECT_EQ(ids[1], 4);
  EXPECT_EQ(ids[2], 12);
  EXPECT_EQ(ids[3], 6);
  EXPECT_EQ(ids[4], 3);
}

TEST(HostArgmax, MatchesPlainLoops) {
  Rng rng(3);
  const TensorF logits = random_tensor<float>({2, kClasses, 5, 3}, rng, -3, 3);
  Tensor<uint8_t> ids;
  argmax_class_ids(logits, ids);
  ASSERT_EQ(ids.shape(), (Shape{2, 5, 3}));
  for (int64_t b = 0; b < 2; ++b) {
    for (int64_t y = 0; y < 5; ++y) {
      for (int64_t x = 0; x < 3; ++x) {
        int64_t best = 0;
        for (int64_t k = 1; k < kClasses; ++k) {
          if (logits(b, k, y, x) > logits(b, best, y, x)) best = k;
        }
        EXPECT_EQ(ids(b, y, x), best + 1);
      }
    }
  }
}

// ---------------------------------------------------------------- losses

TEST(HostLoss, CrossEntropyTwoCellsByHand) {
  const TwoCells cells;
  TensorD grad;
  const double loss = cross_entropy_loss(cells.logits, cells.labels, kWeights, &grad);
  // cell 0: p = 1/12 everywhere, -log p = ln 12, weight 2;
  // cell 1: p(class 5) = 11 / (11 + 11) = 1/2, -log p = ln 2, weight 1.  M = 2.
  EXPECT_NEAR(loss, (2 * std::log(12.0) + std::log(2.0)) / 2, 1e-14);
  for (int64_t k = 0; k < kClasses; ++k) {
    SCOPED_TRACE(k);
    EXPECT_NEAR(grad(0, k, 0, 0), 2.0 / 2 * (1.0 / 12 - (k == 0)), 1e-15);
    EXPECT_NEAR(grad(0, k, 0, 1), 1.0 / 2 * ((k == 4 ? 0.5 : 1.0 / 22) - (k == 4)), 1e-15);
    EXPECT_EQ(grad(0, k, 0, 2), 0.0);
  }
  EXPECT_DOUBLE_EQ(cross_entropy_loss(cells.logits, cells.labels, kWeights, nullptr), loss);
}

TEST(HostLoss, BceTwoCellsByHand) {
  const TwoCells cells;
  TensorD grad;
  const double loss = bce_loss(cells.logits, cells.labels, kWeights, &grad);
  // Every pair with logit 0 costs weight * ln 2; the weights c[1..12] sum to 34. The positive
  // pair of cell 1 (class 5, weight 1, logit ln 11) costs softplus(-ln 11) = ln(12 / 11).
  // Mean over M * K = 2 * 12 pairs.
  const double ln2 = std::log(2.0);
  EXPECT_NEAR(loss, (34 * ln2 + 33 * ln2 + std::log(12.0 / 11)) / 24, 1e-14);
  for (int64_t k = 0; k < kClasses; ++k) {
    SCOPED_TRACE(k);
    const double weight = kWeights[k + 1];
    EXPECT_NEAR(grad(0, k, 0, 0), weight * (0.5 - (k == 0)) / 24, 1e-15);
    EXPECT_NEAR(grad(0, k, 0, 1), k == 4 ? (11.0 / 12 - 1) / 24 : weight * 0.5 / 24, 1e-15);
    EXPECT_EQ(grad(0, k, 0, 2), 0.0);
  }
  EXPECT_DOUBLE_EQ(bce_loss(cells.logits, cells.labels, kWeights, nullptr), loss);
}

TEST(HostLoss, UnlabeledCellsContributeNothing) {
  Rng rng(10);
  const Tensor<uint8_t> labels = random_labels({2, 5, 3}, rng);
  const TensorD logits = random_tensor({2, kClasses, 5, 3}, rng, -3, 3);
  TensorD scrambled = logits;  // other logits in the unlabeled cells only
  for (int64_t b = 0; b < 2; ++b) {
    for (int64_t k = 0; k < kClasses; ++k) {
      for (int64_t i = 0; i < 15; ++i) {
        if (labels[b * 15 + i] == 0) scrambled[(b * kClasses + k) * 15 + i] = rng.uniform(-50, 50);
      }
    }
  }
  for (const NamedLoss& l : kLosses) {
    SCOPED_TRACE(l.name);
    TensorD grad, grad_scrambled;
    EXPECT_EQ(l.loss(logits, labels, kWeights, &grad),
              l.loss(scrambled, labels, kWeights, &grad_scrambled));
    EXPECT_TRUE(test::all_close(grad_scrambled, grad, 0, 0));
    for (int64_t b = 0; b < 2; ++b) {
      for (int64_t k = 0; k < kClasses; ++k) {
        for (int64_t i = 0; i < 15; ++i) {
          if (labels[b * 15 + i] == 0) {
            EXPECT_EQ(grad[(b * kClasses + k) * 15 + i], 0.0);
          }
        }
      }
    }
  }
}

TEST(HostLoss, NoLabelledCellGivesZero) {
  const TensorD logits({2, kClasses, 5, 3}, kNaN);
  const Tensor<uint8_t> labels({2, 5, 3});
  for (const NamedLoss& l : kLosses) {
    SCOPED_TRACE(l.name);
    TensorD grad({1}, 7.0);
    EXPECT_EQ(l.loss(logits, labels, kWeights, &grad), 0.0);
    EXPECT_TRUE(test::all_close(grad, TensorD(logits.shape(), 0.0), 0, 0));
  }
}

TEST(HostLoss, GradientsMatchFiniteDifferences) {
  Rng rng(11);
  const Tensor<uint8_t> labels = random_labels({2, 5, 3}, rng);
  TensorD logits = random_tensor({2, kClasses, 5, 3}, rng, -3, 3);
  for (const NamedLoss& l : kLosses) {
    SCOPED_TRACE(l.name);
    TensorD grad;
    l.loss(logits, labels, kWeights, &grad);
    TensorD numeric(logits.shape());
    const double h = 1e-6;
    for (int64_t i = 0; i < logits.numel(); ++i) {
      const double saved = logits[i];
      logits[i] = saved + h;
      const double plus = l.loss(logits, labels, kWeights, nullptr);
      logits[i] = saved - h;
      const double minus = l.loss(logits, labels, kWeights, nullptr);
      logits[i] = saved;
      numeric[i] = (plus - minus) / (2 * h);
    }
    EXPECT_TRUE(test::all_close(grad, numeric, 1e-8, 1e-6));
  }
}

TEST(HostLoss, StableForLargeLogits) {
  // Two cells, labels 1 and 2; channel 0 has logit 1000 in both, the rest 0.
  TensorF logits({1, kClasses, 1, 2});
  logits(0, 0, 0, 0) = logits(0, 0, 0, 1) = 1000;
  Tensor<uint8_t> labels({1, 1, 2});
  labels[0] = 1, labels[1] = 2;
  TensorF grad;
  // Cross-entropy: cell 0 is certain and right (loss 0), cell 1 misses by 1000 (weight 8).
  EXPECT_NEAR(cross_entropy_loss(logits, labels, kWeights, &grad), 8 * 1000.0 / 2, 1e-3);
  EXPECT_NEAR(grad(0, 0, 0, 1), 8.0 / 2, 1e-6);
  EXPECT_NEAR(grad(0, 1, 0, 1), -8.0 / 2, 1e-6);
  // BCE: channel 0 costs 0 in cell 0 (positive) and c[1] * 1000 in cell 1 (negative). Every
  // logit-0 pair costs its weight * ln 2, positive or not: channels 1..11 weigh 34 - 2 = 32 in
  // each cell.
  const double ln2 = std::log(2.0);
  EXPECT_NEAR(bce_loss(logits, labels, kWeights, &grad), (2 * 1000.0 + 32 * ln2 + 32 * ln2) / 24,
              1e-4);
  EXPECT_NEAR(grad(0, 0, 0, 0), 0.0, 1e-7);
  EXPECT_NEAR(grad(0, 0, 0, 1), 2.0 / 24, 1e-7);
}

TEST(HostLoss, FloatAgreesWithDouble) {
  Rng rng(12);
  const Tensor<uint8_t> labels = random_labels({2, 5, 3}, rng);
  const TensorD logits = random_tensor({2, kClasses, 5, 3}, rng, -5, 5);
  const TensorF logits_f = tensor_cast<float>(logits);
  TensorD grad;
  TensorF grad_f;
  const double ce = cross_entropy_loss(logits, labels, kWeights, &grad);
  EXPECT_NEAR(cross_entropy_loss(logits_f, labels, kWeights, &grad_f), ce, 1e-5 * ce);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(grad_f), grad, 1e-7, 1e-5));
  const double bce = bce_loss(logits, labels, kWeights, &grad);
  EXPECT_NEAR(bce_loss(logits_f, labels, kWeights, &grad_f), bce, 1e-5 * bce);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(grad_f), grad, 1e-7, 1e-5));
}

// The images' statistics and the gradient's planes run in parallel, the loss summed in one
// order: the loss and every gradient bit are the same for any thread count.
TEST(HostLoss, CrossEntropyIsTheSameForAnyThreadCount) {
  Rng rng(5);
  const Tensor<float> logits = random_tensor<float>({3, kClasses, 7, 9}, rng, -4.0, 4.0);
  const Tensor<uint8_t> labels = random_labels({3, 7, 9}, rng);
  const auto run = [&](int threads) {
    const ScopedThreads scoped(threads);
    Tensor<float> d;
    const double loss = cross_entropy_loss<float>(logits, labels, kWeights, &d);
    return std::make_pair(loss, d);
  };
  const auto [loss, d] = run(1);
  for (int threads : {2, 4}) {
    const auto [loss_t, d_t] = run(threads);
    EXPECT_EQ(loss_t, loss) << threads << " threads";
    ASSERT_EQ(d_t.shape(), d.shape());
    EXPECT_EQ(std::memcmp(d_t.data(), d.data(), sizeof(float) * d.numel()), 0) << threads;
  }
}

TEST(HostLoss, RejectsBadArguments) {
  const TensorD logits({1, kClasses, 2, 3});
  Tensor<uint8_t> labels({1, 2, 3});
  for (const NamedLoss& l : kLosses) {
    SCOPED_TRACE(l.name);
    labels(0, 1, 2) = 13;
    EXPECT_THAT(error_message([&] { l.loss(logits, labels, kWeights, nullptr); }),
                HasSubstr("label 13 at (batch 0, iy 1, ix 2) is not a class id in 0..12"));
    labels(0, 1, 2) = 0;
    const std::vector<double> short_weights(kClasses, 1.0);
    EXPECT_THAT(error_message([&] { l.loss(logits, labels, short_weights, nullptr); }),
                HasSubstr("expected 13 class weights (one per class id 0..12), given 12"));
    std::vector<double> negative = kWeights;
    negative[3] = -1;
    EXPECT_THAT(error_message([&] { l.loss(logits, labels, negative, nullptr); }),
                HasSubstr("given -1 for class 3"));
    EXPECT_THAT(error_message([&] {
                  l.loss(logits, Tensor<uint8_t>({1, 3, 2}), kWeights, nullptr);
                }),
                HasSubstr("expected labels of shape (1, 2, 3)"));
  }
}

// ---------------------------------------------------------------- Lovász-softmax

namespace {

// The Lovász-softmax loss as the paper's reference computes it: per present class, the errors
// sorted from the largest down (std::stable_sort), the Jaccard loss's steps as their weights.
double sorted_lovasz(const TensorD& logits, const Tensor<uint8_t>& labels) {
  const int64_t batch = logits.dim(0), classes = logits.dim(1);
  const int64_t plane = logits.dim(2) * logits.dim(3);
  TensorD probs;
  softmax_channels(logits, probs);
  double sum = 0;
  int present = 0;
  for (int64_t k = 0; k < classes; ++k) {
    std::vector<std::pair<double, bool>> errors;  // (error, foreground)
    for (int64_t b = 0; b < batch; ++b) {
      for (int64_t i = 0; i < plane; ++i) {
        const uint8_t y = labels[b * plane + i];
        if (y == 0) continue;
        const double p = probs[(b * classes + k) * plane + i];
        errors.emplace_back(y == k + 1 ? 1 - p : p, y == k + 1);
      }
    }
    const auto foreground = std::count_if(errors.begin(), errors.end(),
                                          [](const auto& e) { return e.second; });
    if (foreground == 0) continue;
    ++present;
    std::stable_sort(errors.begin(), errors.end(),
                     [](const auto& a, const auto& b) { return a.first > b.first; });
    double fg = 0, bg = 0, jaccard_before = 0;
    for (const auto& [error, is_fg] : errors) {
      (is_fg ? fg : bg) += 1;
      const double jaccard = 1 - (static_cast<double>(foreground) - fg) / (foreground + bg);
      sum += error * (jaccard - jaccard_before);
      jaccard_before = jaccard;
    }
  }
  return sum / present;
}

double lovasz(const TensorD& logits, const Tensor<uint8_t>& labels, std::span<const double>,
              TensorD* grad) {
  return lovasz_softmax_loss(logits, labels, grad);
}

}  // namespace

TEST(HostLovasz, ThreeCellsByHand) {
  // Two classes; cells 0 and 1 of class 1 with p(1) = 0.9 and 0.3, cell 2 of class 2 with
  // p(1) = 0.2, cell 3 unlabeled. Class 1: errors 0.1 (fg), 0.7 (fg), 0.2 (bg); from the largest,
  // the Jaccard loss goes 1/2, 2/3, 1: 0.7 / 2 + 0.2 / 6 + 0.1 / 3. Class 2: errors 0.1 (bg), 0.7
  // (bg), 0.2 (fg); the steps 1/2, 1/2, 0: 0.7 / 2 + 0.2 / 2. The loss is their mean.
  TensorD logits({1, 2, 1, 4});
  const double p1[] = {0.9, 0.3, 0.2};
  for (int i = 0; i < 3; ++i) logits(0, 0, 0, i) = std::log(p1[i]), logits(0, 1, 0, i) = std::log(1 - p1[i]);
  logits(0, 0, 0, 3) = kNaN;
  Tensor<uint8_t> labels({1, 1, 4});
  labels[0] = 1, labels[1] = 1, labels[2] = 2, labels[3] = 0;
  TensorD grad;
  const double expected = ((0.35 + 0.2 / 6 + 0.1 / 3) + (0.35 + 0.1)) / 2;
  EXPECT_NEAR(lovasz_softmax_loss(logits, labels, &grad), expected, 1e-12);
  // Cell 0: class 1's error 0.1 (fg) weighs 1/3, class 2's error 0.1 (bg) 0; over the 2 present
  // classes s = (-1/6, 0), sum s p = -0.15, d_k = p_k (s_k + 0.15): -0.015 and +0.015.
  EXPECT_NEAR(grad(0, 0, 0, 0), -0.015, 1e-12);
  EXPECT_NEAR(grad(0, 1, 0, 0), 0.015, 1e-12);
  EXPECT_EQ(grad(0, 0, 0, 3), 0.0);
  EXPECT_EQ(grad(0, 1, 0, 3), 0.0);
}

TEST(HostLovasz, EqualsTheSortedLossWithinABin) {
  Rng rng(13);
  for (int trial = 0; trial < 4; ++trial) {
    SCOPED_TRACE(trial);
    const Tensor<uint8_t> labels = random_labels({2, 6, 5}, rng);
    const TensorD logits = random_tensor({2, kClasses, 6, 5}, rng, -4, 4);
    EXPECT_NEAR(lovasz_softmax_loss(logits, labels, nullptr), sorted_lovasz(logits, labels),
                1.0 / kLovaszBins);
  }
  // Equal errors (equal logits in every cell) leave nothing to order: the two agree exactly.
  const Tensor<uint8_t> labels = random_labels({1, 4, 4}, rng);
  const TensorD flat({1, kClasses, 4, 4}, 0.25);
  EXPECT_NEAR(lovasz_softmax_loss(flat, labels, nullptr), sorted_lovasz(flat, labels), 1e-15);
}

TEST(HostLovasz, GradientMatchesFiniteDifferences) {
  // A step of 1e-8 moves no error across a bin's edge for this seed (the loss is piecewise
  // smooth, with steps of at most 1 / 4096 of a Jaccard step at the edges).
  Rng rng(14);
  const Tensor<uint8_t> labels = random_labels({2, 3, 3}, rng);
  TensorD logits = random_tensor({2, kClasses, 3, 3}, rng, -3, 3);
  TensorD grad;
  lovasz_softmax_loss(logits, labels, &grad);
  const TensorD numeric = numeric_gradient(
      logits, [&] { return lovasz_softmax_loss(logits, labels, nullptr); }, 1e-8);
  EXPECT_TRUE(test::all_close(grad, numeric, 1e-7, 1e-5));
}

TEST(HostLovasz, UnlabeledCellsInertAndFloatAgreesWithDouble) {
  Rng rng(15);
  const Tensor<uint8_t> labels = random_labels({2, 5, 3}, rng);
  const TensorD logits = random_tensor({2, kClasses, 5, 3}, rng, -3, 3);
  TensorD scrambled = logits;
  for (int64_t b = 0; b < 2; ++b) {
    for (int64_t k = 0; k < kClasses; ++k) {
      for (int64_t i = 0; i < 15; ++i) {
        if (labels[b * 15 + i] == 0) scrambled[(b * kClasses + k) * 15 + i] = kNaN;
      }
    }
  }
  TensorD grad, grad_scrambled;
  const double loss = lovasz(logits, labels, kWeights, &grad);
  EXPECT_EQ(lovasz(scrambled, labels, kWeights, &grad_scrambled), loss);
  EXPECT_TRUE(test::all_close(grad_scrambled, grad, 0, 0));
  TensorF grad_f;
  EXPECT_NEAR(lovasz_softmax_loss(tensor_cast<float>(logits), labels, &grad_f), loss, 1e-4);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(grad_f), grad, 1e-5, 1e-3));
  TensorD zero_grad({1}, 7.0);
  EXPECT_EQ(lovasz_softmax_loss(logits, Tensor<uint8_t>(labels.shape()), &zero_grad), 0.0);
  EXPECT_TRUE(test::all_close(zero_grad, TensorD(logits.shape(), 0.0), 0, 0));
}
