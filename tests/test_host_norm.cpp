// host/ BatchNorm, PFN and pillar scatter: forward against plain-loop references and hand-computed
// numbers, backward against central finite differences in double, edge cases (empty batch, one
// pillar, odd sizes) and argument errors.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <barrier>
#include <cmath>
#include <functional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "core/parallel.hpp"
#include "core/rng.hpp"
#include "host/batchnorm.hpp"
#include "host/pfn.hpp"
#include "host/scatter.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using pillarseg::test::dot;
using pillarseg::test::numeric_gradient;
using pillarseg::test::random_tensor;
using namespace pillarseg::host;
using ::testing::HasSubstr;

namespace {

// Message of the pillarseg::Error thrown by fn ("" when nothing is thrown).
std::string error_message(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

// Values of channel c sit at flat index i with c = (i / inner) % C: inner = H * W for
// (B, C, H, W) and 1 for (M, C).
int64_t inner_size(const TensorD& x) {
  return x.rank() == 4 ? x.dim(2) * x.dim(3) : 1;
}

// Plain-loop BatchNorm with statistics over every axis but 1: mean, biased var and y.
struct BatchNormReference {
  std::vector<double> mean, variance;
  TensorD y;
};

BatchNormReference reference_batchnorm(const TensorD& x, const TensorD& gamma, const TensorD& beta,
                                       double eps, bool relu) {
  const int64_t channels = x.dim(1), inner = inner_size(x);
  BatchNormReference r{std::vector<double>(channels), std::vector<double>(channels),
                       TensorD(x.shape())};
  std::vector<int64_t> count(channels);
  for (int64_t i = 0; i < x.numel(); ++i) {
    r.mean[(i / inner) % channels] += x[i];
    ++count[(i / inner) % channels];
  }
  for (int64_t c = 0; c < channels; ++c) r.mean[c] /= static_cast<double>(count[c]);
  for (int64_t i = 0; i < x.numel(); ++i) {
    const int64_t c = (i / inner) % channels;
    r.variance[c] += (x[i] - r.mean[c]) * (x[i] - r.mean[c]);
  }
  for (int64_t c = 0; c < channels; ++c) r.variance[c] /= static_cast<double>(count[c]);
  for (int64_t i = 0; i < x.numel(); ++i) {
    const int64_t c = (i / inner) % channels;
    const double y = gamma[c] * (x[i] - r.mean[c]) / std::sqrt(r.variance[c] + eps) + beta[c];
    r.y[i] = relu ? std::max(y, 0.0) : y;
  }
  return r;
}

struct BatchNormCase {
  Shape shape;
  bool relu;
};

std::string case_name(const BatchNormCase& c) {
  return shape_str(c.shape) + (c.relu ? " relu" : " plain");
}

const std::vector<BatchNormCase> kBatchNormCases = {{{2, 3, 5, 3}, false}, {{2, 3, 5, 3}, true},
                                                    {{7, 3}, false},       {{7, 3}, true},
                                                    {{1, 3, 1, 2}, false}, {{2, 1}, false}};

}  // namespace

// ---------------------------------------------------------------- BatchNorm

TEST(HostBatchNorm, TrainForwardMatchesPlainLoops) {
  for (const BatchNormCase& bn : kBatchNormCases) {
    SCOPED_TRACE(case_name(bn));
    Rng rng(1);
    const int64_t channels = bn.shape[1];
    const TensorD x = random_tensor(bn.shape, rng, -2, 3);
    const TensorD gamma = random_tensor({channels}, rng, 0.5, 1.5);
    const TensorD beta = random_tensor({channels}, rng);
    TensorD running_mean({channels}, 0.0), running_var({channels}, 1.0);
    int64_t batches = 0;
    TensorD y;
    BatchNormSaved<double> saved;
    const BatchNormOptions options{1e-5, 0.1};
    if (bn.relu) {
      batchnorm_relu_forward_train(x, gamma, beta, options, running_mean, running_var, batches, y,
                                   saved);
    } else {
      batchnorm_forward_train(x, gamma, beta, options, running_mean, running_var, batches, y,
                              saved);
    }
    const BatchNormReference ref = reference_batchnorm(x, gamma, beta, options.eps, bn.relu);
    EXPECT_TRUE(test::all_close(y, ref.y, 1e-12, 1e-12));
    for (int64_t c = 0; c < channels; ++c) {
      EXPECT_NEAR(saved.mean[c], ref.mean[c], 1e-13);
      EXPECT_NEAR(saved.inv_std[c], 1 / std::sqrt(ref.variance[c] + options.eps), 1e-12);
    }
    EXPECT_EQ(batches, 1);
  }
}

TEST(HostBatchNorm, InPlaceMatchesOutOfPlace) {
  for (const Shape& shape : {Shape{2, 3, 5, 3}, Shape{7, 3}}) {
    SCOPED_TRACE(shape_str(shape));
    Rng rng(6);
    const TensorD x = random_tensor(shape, rng, -2, 3);
    const TensorD gamma = random_tensor({3}, rng, 0.5, 1.5), beta = random_tensor({3}, rng);
    TensorD mean1({3}, 0.0), var1({3}, 1.0), mean2 = mean1, var2 = var1, y;
    int64_t batches1 = 0, batches2 = 0;
    BatchNormSaved<double> saved1, saved2;
    batchnorm_relu_forward_train(x, gamma, beta, {}, mean1, var1, batches1, y, saved1);
    TensorD in_place = x;
    batchnorm_relu_forward_train(in_place, gamma, beta, {}, mean2, var2, batches2, in_place,
                                 saved2);
    EXPECT_TRUE(test::all_close(in_place, y, 0, 0));
    EXPECT_TRUE(test::all_close(var2, var1, 0, 0));
    in_place = x;
    batchnorm_forward_eval(x, gamma, beta, mean1, var1, {}, y);
    batchnorm_forward_eval(in_place, gamma, beta, mean1, var1, {}, in_place);
    EXPECT_TRUE(test::all_close(in_place, y, 0, 0));
    // In place through two views of one buffer (as the backends call it): not zeroed first.
    in_place = x;
    const TensorD x_view = TensorD::view(in_place.data(), shape);
    TensorD y_view = TensorD::view(in_place.data(), shape);
    batchnorm_relu_forward_eval(x_view, gamma, beta, mean1, var1, {}, y_view);
    TensorD relu_y;
    batchnorm_relu_forward_eval(x, gamma, beta, mean1, var1, {}, relu_y);
    EXPECT_TRUE(test::all_close(in_place, relu_y, 0, 0));

    TensorD dy = random_tensor(shape, rng), dx, dgamma, dbeta;
    batchnorm_backward(dy, x, gamma, saved1, dx, dgamma, dbeta);
    batchnorm_backward(dy, x, gamma, saved1, dy, dgamma, dbeta);
    EXPECT_TRUE(test::all_close(dy, dx, 0, 0));
  }
}

// Large enough (>= 2^15 values) that ranges of channels run in parallel; every channel is
// computed whole by one thread, as with one thread: the same bits for any thread count.
TEST(HostBatchNorm, SameBitsForEveryThreadCount) {
  const int saved_threads = num_threads();
  Rng rng(12);
  const Shape shape{2, 7, 41, 59};
  const Tensor<float> x = random_tensor<float>(shape, rng, -2, 3);
  const Tensor<float> dy = random_tensor<float>(shape, rng);
  const Tensor<float> gamma = random_tensor<float>({7}, rng, 0.5, 1.5);
  const Tensor<float> beta = random_tensor<float>({7}, rng);
  std::vector<Tensor<float>> results;
  for (int threads : {1, 2, 3}) {
    set_num_threads(threads);
    Tensor<float> mean({7}, 0.0f), var({7}, 1.0f), y, dx, dgamma, dbeta, eval;
    int64_t batches = 0;
    BatchNormSaved<float> saved;
    batchnorm_relu_forward_train(x, gamma, beta, {}, mean, var, batches, y, saved);
    batchnorm_relu_backward(dy, x, y, gamma, saved, dx, dgamma, dbeta);
    batchnorm_relu_forward_eval(x, gamma, beta, mean, var, {}, eval);
    for (const Tensor<float>* t : {&y, &mean, &var, &saved.inv_std, &dx, &dgamma, &dbeta, &eval})
      results.push_back(*t);
  }
  set_num_threads(saved_threads);
  const size_t per_run = results.size() / 3;
  for (size_t i = 0; i < per_run; ++i) {
    EXPECT_EQ(results[i], results[per_run + i]) << "result " << i << ", 2 threads";
    EXPECT_EQ(results[i], results[2 * per_run + i]) << "result " << i << ", 3 threads";
  }
}

// R replicas of a data-parallel run as R threads of this process: each sum() waits for all of
// them and adds their values in replica order, as engine/mpi/ does across processes.
class ThreadReplicas {
 public:
  explicit ThreadReplicas(int size) : slots_(static_cast<size_t>(size)), barrier_(size) {
    for (int r = 0; r < size; ++r) members_.push_back(Member(this, r));
  }
  ReplicaSum* member(int rank) { return &members_[static_cast<size_t>(rank)]; }

 private:
  class Member final : public ReplicaSum {
   public:
    Member(ThreadReplicas* all, int rank) : all_(all), rank_(rank) {}
    void sum(double* values, int64_t n) override { all_->sum(rank_, values, n); }

   private:
    ThreadReplicas* all_;
    int rank_;
  };
  void sum(int rank, double* values, int64_t n) {
    slots_[static_cast<size_t>(rank)].assign(values, values + n);
    barrier_.arrive_and_wait();
    for (int64_t i = 0; i < n; ++i) {
      double total = slots_[0][static_cast<size_t>(i)];
      for (size_t r = 1; r < slots_.size(); ++r) total += slots_[r][static_cast<size_t>(i)];
      values[i] = total;
    }
    barrier_.arrive_and_wait();
  }
  std::vector<std::vector<double>> slots_;
  std::barrier<> barrier_;
  std::vector<Member> members_;
};

// Rows [begin, end) of axis 0 of x.
Tensor<float> rows(const Tensor<float>& x, int64_t begin, int64_t end) {
  Shape shape = x.shape();
  const int64_t per_row = x.numel() / shape[0];
  shape[0] = end - begin;
  Tensor<float> out(shape);
  std::copy(x.data() + begin * per_row, x.data() + end * per_row, out.data());
  return out;
}

// Synchronised BatchNorm: replicas that each hold some rows of a batch get the statistics, the
// outputs and the input gradients of the whole batch, and their dgamma / dbeta add up to its.
// With one batch item per replica of a (B, C, H, W) input, the per-channel sums are the same
// additions in the same order (double), so every result is the same bits; for (M, C) (the PFN)
// the row sums are regrouped, which double accumulation leaves below float rounding, except for
// a rare tie. One (M, C) replica holds no rows (a scan without pillars) and still joins the sums.
TEST(HostBatchNorm, SynchronisedOverReplicasIsTheWholeBatch) {
  struct Split {
    Shape shape;
    std::vector<int64_t> bounds;  // replica r holds rows [bounds[r], bounds[r + 1])
    bool exact;
  };
  for (const Split& split :
       {Split{{3, 5, 7, 6}, {0, 1, 2, 3}, true}, Split{{40, 4}, {0, 13, 13, 30, 40}, false}}) {
    SCOPED_TRACE(shape_str(split.shape));
    const int64_t C = split.shape[1];
    const int R = static_cast<int>(split.bounds.size()) - 1;
    Rng rng(31);
    const Tensor<float> x = random_tensor<float>(split.shape, rng, -2, 3);
    const Tensor<float> dy = random_tensor<float>(split.shape, rng);
    const Tensor<float> gamma = random_tensor<float>({C}, rng, 0.5, 1.5);
    const Tensor<float> beta = random_tensor<float>({C}, rng);
    struct Result {
      Tensor<float> y, dx, dgamma, dbeta, mean, var;
      BatchNormSaved<float> saved;
    };
    const auto run = [&](const Tensor<float>& xs, const Tensor<float>& dys, ReplicaSum* replicas) {
      Result r;
      r.mean = Tensor<float>({C}, 0.25f), r.var = Tensor<float>({C}, 1.5f);
      int64_t batches = 0;
      BatchNormOptions options;
      options.replicas = replicas;
      batchnorm_relu_forward_train(xs, gamma, beta, options, r.mean, r.var, batches, r.y, r.saved);
      batchnorm_relu_backward(dys, xs, r.y, gamma, r.saved, r.dx, r.dgamma, r.dbeta, replicas);
      return r;
    };
    const Result whole = run(x, dy, nullptr);
    std::vector<Result> parts(static_cast<size_t>(R));
    ThreadReplicas replicas(R);
    std::vector<std::thread> threads;
    for (int r = 0; r < R; ++r) {
      threads.emplace_back([&, r] {
        const int64_t begin = split.bounds[static_cast<size_t>(r)],
                      end = split.bounds[static_cast<size_t>(r) + 1];
        parts[static_cast<size_t>(r)] =
            run(rows(x, begin, end), rows(dy, begin, end), replicas.member(r));
      });
    }
    for (std::thread& t : threads) t.join();
    const double tolerance = split.exact ? 0.0 : 1e-6;
    Tensor<double> dgamma_sum({C}, 0.0), dbeta_sum({C}, 0.0);
    for (int r = 0; r < R; ++r) {
      SCOPED_TRACE("replica " + std::to_string(r));
      const Result& part = parts[static_cast<size_t>(r)];
      const int64_t begin = split.bounds[static_cast<size_t>(r)],
                    end = split.bounds[static_cast<size_t>(r) + 1];
      const std::pair<const Tensor<float>*, const Tensor<float>*> statistics[] = {
          {&part.mean, &whole.mean},
          {&part.var, &whole.var},
          {&part.saved.mean, &whole.saved.mean},
          {&part.saved.inv_std, &whole.saved.inv_std}};
      for (const auto& [mine, batch] : statistics)
        EXPECT_TRUE(test::all_close(*mine, *batch, tolerance, tolerance));
      EXPECT_TRUE(test::all_close(part.y, rows(whole.y, begin, end), tolerance, tolerance));
      EXPECT_TRUE(test::all_close(part.dx, rows(whole.dx, begin, end), tolerance, tolerance));
      for (int64_t c = 0; c < C; ++c)
        dgamma_sum[c] += part.dgamma[c], dbeta_sum[c] += part.dbeta[c];
    }
    for (int64_t c = 0; c < C; ++c) {  // each replica's share is rounded to float once
      EXPECT_NEAR(dgamma_sum[c], whole.dgamma[c], 1e-5 * (1 + std::abs(whole.dgamma[c])));
      EXPECT_NEAR(dbeta_sum[c], whole.dbeta[c], 1e-5 * (1 + std::abs(whole.dbeta[c])));
    }
    // Without the replicas, a share normalises with its own statistics: the test sees that.
    const Result alone = run(rows(x, split.bounds[0], split.bounds[1]),
                             rows(dy, split.bounds[0], split.bounds[1]), nullptr);
    EXPECT_FALSE(test::all_close(alone.saved.mean, whole.saved.mean, 1e-3, 1e-3));
  }
}

TEST(HostBatchNorm, RunningStatisticsUseTheUnbiasedVariance) {
  // (M, C) = (4, 2): channel 0 = {1, 2, 3, 6}: mean 3, biased var 14/4, unbiased var 14/3;
  //                  channel 1 = {0, 0, 4, 4}: mean 2, biased var 16/4, unbiased var 16/3.
  TensorD x({4, 2});
  const double values[] = {1, 0, 2, 0, 3, 4, 6, 4};
  for (int i = 0; i < 8; ++i) x[i] = values[i];
  const TensorD gamma({2}, 1.0), beta({2}, 0.0);
  TensorD running_mean({2}), running_var({2});
  running_mean[0] = 0.5, running_mean[1] = -1;
  running_var[0] = 1, running_var[1] = 2;
  int64_t batches = 5;
  TensorD y;
  BatchNormSaved<double> saved;
  batchnorm_forward_train(x, gamma, beta, {1e-5, 0.1}, running_mean, running_var, batches, y,
                          saved);
  EXPECT_NEAR(running_mean[0], 0.9 * 0.5 + 0.1 * 3, 1e-15);      // 0.75
  EXPECT_NEAR(running_mean[1], 0.9 * -1 + 0.1 * 2, 1e-15);       // -0.7
  EXPECT_NEAR(running_var[0], 0.9 * 1 + 0.1 * 14.0 / 3, 1e-15);  // 1.3666...
  EXPECT_NEAR(running_var[1], 0.9 * 2 + 0.1 * 16.0 / 3, 1e-15);  // 2.3333...
  EXPECT_EQ(batches, 6);
  EXPECT_NEAR(y(0, 0), (1 - 3) / std::sqrt(3.5 + 1e-5), 1e-14);  // normalised by the biased var
  EXPECT_NEAR(y(3, 1), (4 - 2) / std::sqrt(4.0 + 1e-5), 1e-14);

  // (B, C, H, W) = (2, 1, 1, 2), PFN settings: {1, 3} and {5, 7}: mean 4, biased var 5,
  // unbiased var 20/3.
  TensorD image({2, 1, 1, 2});
  image[0] = 1, image[1] = 3, image[2] = 5, image[3] = 7;
  TensorD mean1({1}, 0.0), var1({1}, 1.0);
  int64_t batches1 = 0;
  batchnorm_forward_train(image, TensorD({1}, 1.0), TensorD({1}, 0.0), kPfnNormOptions, mean1, var1,
                          batches1, y, saved);
  EXPECT_NEAR(mean1[0], 0.01 * 4, 1e-15);
  EXPECT_NEAR(var1[0], 0.99 + 0.01 * 20.0 / 3, 1e-15);
  EXPECT_NEAR(saved.mean[0], 4, 1e-15);
  EXPECT_NEAR(saved.inv_std[0], 1 / std::sqrt(5 + 1e-3), 1e-15);
}

TEST(HostBatchNorm, EvalUsesTheRunningStatistics) {
  for (const BatchNormCase& bn : kBatchNormCases) {
    SCOPED_TRACE(case_name(bn));
    Rng rng(2);
    const int64_t channels = bn.shape[1];
    const TensorD x = random_tensor(bn.shape, rng, -2, 3);
    const TensorD gamma = random_tensor({channels}, rng, 0.5, 1.5);
    const TensorD beta = random_tensor({channels}, rng);
    const TensorD running_mean = random_tensor({channels}, rng);
    const TensorD running_var = random_tensor({channels}, rng, 0.5, 2);
    const BatchNormOptions options{1e-3, 0.01};
    TensorD y;
    if (bn.relu) {
      batchnorm_relu_forward_eval(x, gamma, beta, running_mean, running_var, options, y);
    } else {
      batchnorm_forward_eval(x, gamma, beta, running_mean, running_var, options, y);
    }
    TensorD expected(x.shape());
    const int64_t inner = inner_size(x);
    for (int64_t i = 0; i < x.numel(); ++i) {
      const int64_t c = (i / inner) % channels;
      const double v =
          gamma[c] * (x[i] - running_mean[c]) / std::sqrt(running_var[c] + options.eps) + beta[c];
      expected[i] = bn.relu ? std::max(v, 0.0) : v;
    }
    EXPECT_TRUE(test::all_close(y, expected, 1e-13, 1e-13));
  }
}

TEST(HostBatchNorm, BackwardMatchesFiniteDifferences) {
  for (const BatchNormCase& bn : kBatchNormCases) {
    SCOPED_TRACE(case_name(bn));
    Rng rng(3);
    const int64_t channels = bn.shape[1];
    TensorD x = random_tensor(bn.shape, rng, -2, 3);
    TensorD gamma = random_tensor({channels}, rng, 0.5, 1.5);
    TensorD beta = random_tensor({channels}, rng);
    const TensorD weights = random_tensor(bn.shape, rng);  // f = sum(weights * y)
    const BatchNormOptions options{1e-5, 0.1};
    const TensorD initial_mean({channels}, 0.0), initial_var({channels}, 1.0);

    auto forward = [&](TensorD& y, BatchNormSaved<double>& saved) {
      TensorD running_mean = initial_mean, running_var = initial_var;
      int64_t batches = 0;
      if (bn.relu) {
        batchnorm_relu_forward_train(x, gamma, beta, options, running_mean, running_var, batches, y,
                                     saved);
      } else {
        batchnorm_forward_train(x, gamma, beta, options, running_mean, running_var, batches, y,
                                saved);
      }
    };
    auto f = [&]() {
      TensorD y;
      BatchNormSaved<double> saved;
      forward(y, saved);
      return dot(weights, y);
    };

    TensorD y, dx, dgamma, dbeta;
    BatchNormSaved<double> saved;
    forward(y, saved);
    if (bn.relu) {
      batchnorm_relu_backward(weights, x, y, gamma, saved, dx, dgamma, dbeta);
    } else {
      batchnorm_backward(weights, x, gamma, saved, dx, dgamma, dbeta);
    }
    EXPECT_TRUE(test::all_close(dx, numeric_gradient(x, f), 1e-7, 1e-6));
    EXPECT_TRUE(test::all_close(dgamma, numeric_gradient(gamma, f), 1e-7, 1e-6));
    EXPECT_TRUE(test::all_close(dbeta, numeric_gradient(beta, f), 1e-7, 1e-6));
  }
}

TEST(HostBatchNorm, FloatAgreesWithDouble) {
  Rng rng(4);
  const Shape shape{2, 3, 5, 3};
  const TensorD x = random_tensor(shape, rng, -2, 3);
  const TensorD gamma = random_tensor({3}, rng, 0.5, 1.5);
  const TensorD beta = random_tensor({3}, rng);
  const TensorD dy = random_tensor(shape, rng);

  TensorD mean_d({3}, 0.0), var_d({3}, 1.0), y_d, dx_d, dgamma_d, dbeta_d;
  int64_t batches_d = 0;
  BatchNormSaved<double> saved_d;
  batchnorm_relu_forward_train(x, gamma, beta, {}, mean_d, var_d, batches_d, y_d, saved_d);
  batchnorm_relu_backward(dy, x, y_d, gamma, saved_d, dx_d, dgamma_d, dbeta_d);

  TensorF mean_f({3}, 0.0f), var_f({3}, 1.0f), y_f, dx_f, dgamma_f, dbeta_f;
  int64_t batches_f = 0;
  BatchNormSaved<float> saved_f;
  const TensorF x_f = tensor_cast<float>(x), gamma_f = tensor_cast<float>(gamma);
  batchnorm_relu_forward_train(x_f, gamma_f, tensor_cast<float>(beta), {}, mean_f, var_f, batches_f,
                               y_f, saved_f);
  batchnorm_relu_backward(tensor_cast<float>(dy), x_f, y_f, gamma_f, saved_f, dx_f, dgamma_f,
                          dbeta_f);

  EXPECT_TRUE(test::all_close(tensor_cast<double>(y_f), y_d, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(mean_f), mean_d, 1e-6, 1e-6));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(var_f), var_d, 1e-6, 1e-6));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dx_f), dx_d, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dgamma_f), dgamma_d, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dbeta_f), dbeta_d, 1e-5, 1e-5));
}

TEST(HostBatchNorm, FloatKeepsPrecisionForALargeMean) {
  // Values 1000 + U(-1, 1): float must not lose the spread against the offset.
  Rng rng(5);
  const TensorD x = random_tensor({2, 3, 5, 3}, rng, 999, 1001);
  const TensorD gamma({3}, 1.0), beta({3}, 0.0);
  TensorF mean({3}, 0.0f), var({3}, 1.0f), y;
  int64_t batches = 0;
  BatchNormSaved<float> saved;
  batchnorm_forward_train(tensor_cast<float>(x), tensor_cast<float>(gamma),
                          tensor_cast<float>(beta), {}, mean, var, batches, y, saved);
  const BatchNormReference ref =
      reference_batchnorm(tensor_cast<double>(tensor_cast<float>(x)), gamma, beta, 1e-5, false);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(y), ref.y, 2e-4, 0));
}

TEST(HostBatchNorm, EmptyBatchKeepsRunningStatistics) {
  for (const Shape& shape : {Shape{0, 3}, Shape{0, 3, 5, 3}}) {
    SCOPED_TRACE(shape_str(shape));
    const TensorD x(shape), gamma({3}, 1.0), beta({3}, 0.0);
    TensorD running_mean({3}, 0.25), running_var({3}, 2.0);
    int64_t batches = 7;
    TensorD y, dx, dgamma, dbeta;
    BatchNormSaved<double> saved;
    batchnorm_relu_forward_train(x, gamma, beta, {}, running_mean, running_var, batches, y, saved);
    EXPECT_EQ(y.shape(), shape);
    EXPECT_EQ(batches, 8);  // torch counts the call
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(running_mean[c], 0.25);
      EXPECT_EQ(running_var[c], 2.0);
      EXPECT_TRUE(std::isfinite(saved.mean[c]) && std::isfinite(saved.inv_std[c]));
    }
    batchnorm_relu_backward(TensorD(shape), x, y, gamma, saved, dx, dgamma, dbeta);
    EXPECT_EQ(dx.shape(), shape);
    EXPECT_TRUE(test::all_close(dgamma, TensorD({3}, 0.0), 0, 0));
    EXPECT_TRUE(test::all_close(dbeta, TensorD({3}, 0.0), 0, 0));
  }
}

TEST(HostBatchNorm, ReluPassesNaN) {
  TensorD x({3, 1});
  x[0] = -1, x[1] = std::nan(""), x[2] = 1;
  TensorD y;
  batchnorm_relu_forward_eval(x, TensorD({1}, 1.0), TensorD({1}, 0.0), TensorD({1}, 0.0),
                              TensorD({1}, 1.0), {}, y);
  EXPECT_EQ(y[0], 0.0);
  EXPECT_TRUE(std::isnan(y[1]));
  EXPECT_GT(y[2], 0.0);
}

TEST(HostBatchNorm, RejectsBadArguments) {
  const TensorD gamma({3}, 1.0), beta({3}, 0.0);
  TensorD running_mean({3}, 0.0), running_var({3}, 1.0), y;
  int64_t batches = 0;
  BatchNormSaved<double> saved;
  auto train = [&](const TensorD& x, const TensorD& g) {
    return error_message([&] {
      batchnorm_forward_train(x, g, beta, {}, running_mean, running_var, batches, y, saved);
    });
  };
  EXPECT_THAT(train(TensorD({1, 3}), gamma), HasSubstr("more than 1 value per channel"));
  EXPECT_THAT(train(TensorD({1, 3, 1, 1}), gamma), HasSubstr("more than 1 value per channel"));
  EXPECT_THAT(train(TensorD({4, 3}), TensorD({4})),
              HasSubstr("batchnorm_forward_train: expected gamma of shape (3)"));
  EXPECT_THAT(train(TensorD({4, 3, 2}), gamma), HasSubstr("(B, C, H, W) or (M, C)"));
  EXPECT_THAT(error_message([&] {
                batchnorm_forward_eval(TensorD({4, 3}), gamma, beta, running_mean, running_var,
                                       {.eps = 0, .momentum = 0.1}, y);
              }),
              HasSubstr("eps > 0"));
  TensorD dx, dgamma, dbeta;
  EXPECT_THAT(
      error_message([&] {
        batchnorm_backward(TensorD({4, 3}), TensorD({5, 3}), gamma, saved, dx, dgamma, dbeta);
      }),
      HasSubstr("batchnorm_backward: expected dy of the shape of x"));
  EXPECT_EQ(batches, 0);
}

// ---------------------------------------------------------------- PFN

namespace {

struct PfnProblem {
  TensorD input, weight, gamma, beta;
};

// P pillars of N slots, the first `points[p]` slots real, the rest zero padding.
PfnProblem random_pfn_problem(int64_t pillars, int64_t slots, int64_t channels, uint64_t seed) {
  Rng rng(seed);
  PfnProblem problem{TensorD({pillars, slots, 10}), random_tensor({channels, 10}, rng),
                     random_tensor({channels}, rng, 0.5, 1.5), random_tensor({channels}, rng)};
  for (int64_t p = 0; p < pillars; ++p) {
    const int64_t points = 1 + static_cast<int64_t>(rng.uniform_int(static_cast<uint64_t>(slots)));
    for (int64_t n = 0; n < points; ++n) {
      for (int64_t d = 0; d < 10; ++d) problem.input(p, n, d) = rng.uniform(-2, 2);
    }
  }
  return problem;
}

// Plain loops: z = input . weight^T, BatchNorm over all P * N rows with the given statistics
// (batch statistics when mean is null), ReLU, max over the N slots.
TensorD reference_pfn(const PfnProblem& pr, double eps, const std::vector<double>* mean,
                      const std::vector<double>* variance, std::vector<double>* batch_mean,
                      std::vector<double>* batch_variance) {
  const int64_t pillars = pr.input.dim(0), slots = pr.input.dim(1);
  const int64_t channels = pr.weight.dim(0);
  TensorD z({pillars * slots, channels});
  for (int64_t r = 0; r < pillars * slots; ++r) {
    for (int64_t c = 0; c < channels; ++c) {
      for (int64_t d = 0; d < 10; ++d) z(r, c) += pr.input[r * 10 + d] * pr.weight(c, d);
    }
  }
  std::vector<double> m(channels), v(channels);
  if (mean) {
    m = *mean, v = *variance;
  } else {
    const BatchNormReference bn = reference_batchnorm(z, pr.gamma, pr.beta, eps, false);
    m = bn.mean, v = bn.variance;
    *batch_mean = m, *batch_variance = v;
  }
  TensorD out({pillars, channels}, -1.0);
  for (int64_t p = 0; p < pillars; ++p) {
    for (int64_t n = 0; n < slots; ++n) {
      for (int64_t c = 0; c < channels; ++c) {
        const double a =
            pr.gamma[c] * (z(p * slots + n, c) - m[c]) / std::sqrt(v[c] + eps) + pr.beta[c];
        out(p, c) = std::max(out(p, c), std::max(a, 0.0));
      }
    }
  }
  return out;
}

}  // namespace

TEST(HostPfn, TrainForwardMatchesPlainLoops) {
  const PfnProblem pr = random_pfn_problem(7, 4, 3, 10);
  TensorD running_mean({3}, 0.0), running_var({3}, 1.0), out;
  int64_t batches = 0;
  PfnSaved<double> saved;
  pfn_forward_train(pr.input, pr.weight, pr.gamma, pr.beta, kPfnNormOptions, running_mean,
                    running_var, batches, out, saved);
  std::vector<double> mean, variance;
  const TensorD expected = reference_pfn(pr, 1e-3, nullptr, nullptr, &mean, &variance);
  EXPECT_TRUE(test::all_close(out, expected, 1e-12, 1e-12));
  const double rows = 7 * 4;  // padding rows included in the statistics
  for (int c = 0; c < 3; ++c) {
    EXPECT_NEAR(running_mean[c], 0.01 * mean[c], 1e-14);
    EXPECT_NEAR(running_var[c], 0.99 + 0.01 * variance[c] * rows / (rows - 1), 1e-14);
  }
  EXPECT_EQ(batches, 1);
  ASSERT_EQ(saved.max_slot.shape(), (Shape{7, 3}));
  for (int p = 0; p < 7; ++p) {
    for (int c = 0; c < 3; ++c) EXPECT_EQ(saved.max_slot(p, c) < 0, out(p, c) == 0.0);
  }
}

TEST(HostPfn, EvalUsesTheRunningStatistics) {
  const PfnProblem pr = random_pfn_problem(7, 4, 3, 11);
  Rng rng(12);
  const TensorD running_mean = random_tensor({3}, rng);
  const TensorD running_var = random_tensor({3}, rng, 0.5, 2);
  TensorD out;
  pfn_forward_eval(pr.input, pr.weight, pr.gamma, pr.beta, running_mean, running_var,
                   kPfnNormOptions, out);
  const std::vector<double> mean(running_mean.data(), running_mean.data() + 3);
  const std::vector<double> variance(running_var.data(), running_var.data() + 3);
  EXPECT_TRUE(test::all_close(out, reference_pfn(pr, 1e-3, &mean, &variance, nullptr, nullptr),
                              1e-12, 1e-12));
}

TEST(HostPfn, BackwardMatchesFiniteDifferences) {
  struct Case {
    int64_t pillars, slots, channels;
  };
  for (const Case& size : {Case{7, 4, 3}, Case{1, 4, 3}, Case{3, 1, 5}}) {
    SCOPED_TRACE(fmt::format("P {} N {} C {}", size.pillars, size.slots, size.channels));
    PfnProblem pr = random_pfn_problem(size.pillars, size.slots, size.channels, 20);
    Rng rng(21);
    const TensorD weights = random_tensor({size.pillars, size.channels}, rng);  // f = <w, out>
    auto forward = [&](TensorD& out, PfnSaved<double>& saved) {
      TensorD running_mean({size.channels}, 0.0), running_var({size.channels}, 1.0);
      int64_t batches = 0;
      pfn_forward_train(pr.input, pr.weight, pr.gamma, pr.beta, kPfnNormOptions, running_mean,
                        running_var, batches, out, saved);
    };
    auto f = [&]() {
      TensorD out;
      PfnSaved<double> saved;
      forward(out, saved);
      return dot(weights, out);
    };
    TensorD out, d_input, d_weight, d_gamma, d_beta;
    PfnSaved<double> saved;
    forward(out, saved);
    pfn_backward(weights, pr.input, pr.weight, pr.gamma, saved, d_input, d_weight, d_gamma, d_beta);
    EXPECT_TRUE(test::all_close(d_input, numeric_gradient(pr.input, f), 1e-7, 1e-6));
    EXPECT_TRUE(test::all_close(d_weight, numeric_gradient(pr.weight, f), 1e-7, 1e-6));
    EXPECT_TRUE(test::all_close(d_gamma, numeric_gradient(pr.gamma, f), 1e-7, 1e-6));
    EXPECT_TRUE(test::all_close(d_beta, numeric_gradient(pr.beta, f), 1e-7, 1e-6));
  }
}

TEST(HostPfn, TiesGoToTheFirstSlotAndZeroMaxesPassNoGradient) {
  // Pillar 0 holds one point twice (slots 0 and 1) and two padding slots; pillar 1 one point
  // and three padding slots. Channel 0 sums the features, channel 1 negates the sum:
  //   z(:, 0) = {10, 10, 0, 0, -20, 0, 0, 0}, mean exactly 0, so BatchNorm gives z * inv_std;
  //   pillar 0 has its channel-0 max in slots 0 and 1, pillar 1 its channel-1 max in slot 0,
  //   and the other two maxima are the padding rows' exact 0.
  TensorD input({2, 4, 10});
  for (int d = 0; d < 10; ++d) {
    input(0, 0, d) = input(0, 1, d) = 1;
    input(1, 0, d) = -2;
  }
  TensorD weight({2, 10});
  for (int d = 0; d < 10; ++d) weight(0, d) = 1, weight(1, d) = -1;
  const TensorD gamma({2}, 1.0), beta({2}, 0.0);
  TensorD running_mean({2}, 0.0), running_var({2}, 1.0), out;
  int64_t batches = 0;
  PfnSaved<double> saved;
  pfn_forward_train(input, weight, gamma, beta, kPfnNormOptions, running_mean, running_var, batches,
                    out, saved);
  const double inv_std = saved.norm.inv_std[0];
  EXPECT_EQ(saved.norm.mean[0], 0.0);
  EXPECT_NEAR(out(0, 0), 10 * inv_std, 1e-12);
  EXPECT_EQ(saved.max_slot(0, 0), 0);
  EXPECT_NEAR(out(1, 1), 20 * saved.norm.inv_std[1], 1e-12);
  EXPECT_EQ(saved.max_slot(1, 1), 0);
  EXPECT_EQ(out(0, 1), 0.0);
  EXPECT_EQ(saved.max_slot(0, 1), -1);
  EXPECT_EQ(out(1, 0), 0.0);
  EXPECT_EQ(saved.max_slot(1, 0), -1);

  // A gradient on out(0, 0) alone reaches slot 0 and not its twin, slot 1: the two rows share
  // the BatchNorm statistics terms and differ by the direct term gamma * inv_std * W(0, :).
  TensorD d_out({2, 2});
  d_out(0, 0) = 1;
  TensorD d_input, d_weight, d_gamma, d_beta;
  pfn_backward(d_out, input, weight, gamma, saved, d_input, d_weight, d_gamma, d_beta);
  for (int d = 0; d < 10; ++d) {
    EXPECT_NEAR(d_input(0, 0, d) - d_input(0, 1, d), inv_std * weight(0, d), 1e-12);
  }
}

// With the caller's scratch (stale values in it), forward and backward give what they give
// allocating their own, bit for bit.
TEST(HostPfn, ScratchGivesTheSameResults) {
  Rng rng(5);
  const int64_t P = 7, N = 4, C = 6;
  const TensorF input = tensor_cast<float>(random_tensor({P, N, 10}, rng));
  const TensorF weight = tensor_cast<float>(random_tensor({C, 10}, rng));
  const TensorF gamma = tensor_cast<float>(random_tensor({C}, rng, 0.5, 1.5));
  const TensorF beta = tensor_cast<float>(random_tensor({C}, rng));
  const TensorF d_out = tensor_cast<float>(random_tensor({P, C}, rng));
  struct Run {
    TensorF out, d_input, d_weight, d_gamma, d_beta, mean, var;
  };
  const auto run = [&](float* scratch) {
    Run r;
    r.mean = TensorF({C}, 0.0f), r.var = TensorF({C}, 1.0f);
    int64_t batches = 0;
    PfnSaved<float> saved;
    pfn_forward_train(input, weight, gamma, beta, kPfnNormOptions, r.mean, r.var, batches, r.out,
                      saved, scratch);
    pfn_backward(d_out, input, weight, gamma, saved, r.d_input, r.d_weight, r.d_gamma, r.d_beta,
                 scratch);
    return r;
  };
  const Run own = run(nullptr);
  std::vector<float> scratch(static_cast<size_t>(2 * P * N * C), 123.0f);
  const Run given = run(scratch.data());
  EXPECT_TRUE(test::all_close(given.out, own.out, 0, 0));
  EXPECT_TRUE(test::all_close(given.mean, own.mean, 0, 0));
  EXPECT_TRUE(test::all_close(given.var, own.var, 0, 0));
  EXPECT_TRUE(test::all_close(given.d_input, own.d_input, 0, 0));
  EXPECT_TRUE(test::all_close(given.d_weight, own.d_weight, 0, 0));
  EXPECT_TRUE(test::all_close(given.d_gamma, own.d_gamma, 0, 0));
  EXPECT_TRUE(test::all_close(given.d_beta, own.d_beta, 0, 0));
}

TEST(HostPfn, NoPillars) {
  const TensorD input({0, 4, 10}), weight({3, 10}, 0.5), gamma({3}, 1.0), beta({3}, 0.0);
  TensorD running_mean({3}, 0.25), running_var({3}, 2.0), out;
  int64_t batches = 0;
  PfnSaved<double> saved;
  pfn_forward_train(input, weight, gamma, beta, kPfnNormOptions, running_mean, running_var, batches,
                    out, saved);
  EXPECT_EQ(out.shape(), (Shape{0, 3}));
  for (int c = 0; c < 3; ++c) {
    EXPECT_EQ(running_mean[c], 0.25);
    EXPECT_EQ(running_var[c], 2.0);
  }
  TensorD d_input, d_weight, d_gamma, d_beta;
  pfn_backward(TensorD({0, 3}), input, weight, gamma, saved, d_input, d_weight, d_gamma, d_beta);
  EXPECT_EQ(d_input.shape(), (Shape{0, 4, 10}));
  EXPECT_TRUE(test::all_close(d_weight, TensorD({3, 10}, 0.0), 0, 0));
  EXPECT_TRUE(test::all_close(d_gamma, TensorD({3}, 0.0), 0, 0));
  EXPECT_TRUE(test::all_close(d_beta, TensorD({3}, 0.0), 0, 0));
  pfn_forward_eval(input, weight, gamma, beta, running_mean, running_var, kPfnNormOptions, out);
  EXPECT_EQ(out.shape(), (Shape{0, 3}));
}

TEST(HostPfn, FloatAgreesWithDouble) {
  const PfnProblem pr = random_pfn_problem(7, 4, 3, 30);
  Rng rng(31);
  const TensorD d_out = random_tensor({7, 3}, rng);
  TensorD mean_d({3}, 0.0), var_d({3}, 1.0), out_d, di_d, dw_d, dg_d, db_d;
  TensorF mean_f({3}, 0.0f), var_f({3}, 1.0f), out_f, di_f, dw_f, dg_f, db_f;
  int64_t batches_d = 0, batches_f = 0;
  PfnSaved<double> saved_d;
  PfnSaved<float> saved_f;
  pfn_forward_train(pr.input, pr.weight, pr.gamma, pr.beta, kPfnNormOptions, mean_d, var_d,
                    batches_d, out_d, saved_d);
  pfn_backward(d_out, pr.input, pr.weight, pr.gamma, saved_d, di_d, dw_d, dg_d, db_d);
  const TensorF input_f = tensor_cast<float>(pr.input), weight_f = tensor_cast<float>(pr.weight);
  const TensorF gamma_f = tensor_cast<float>(pr.gamma);
  pfn_forward_train(input_f, weight_f, gamma_f, tensor_cast<float>(pr.beta), kPfnNormOptions,
                    mean_f, var_f, batches_f, out_f, saved_f);
  pfn_backward(tensor_cast<float>(d_out), input_f, weight_f, gamma_f, saved_f, di_f, dw_f, dg_f,
               db_f);
  EXPECT_TRUE(test::all_close(tensor_cast<double>(out_f), out_d, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(di_f), di_d, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dw_f), dw_d, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(dg_f), dg_d, 1e-5, 1e-5));
  EXPECT_TRUE(test::all_close(tensor_cast<double>(db_f), db_d, 1e-5, 1e-5));
}

TEST(HostPfn, RejectsBadArguments) {
  const TensorD gamma({3}, 1.0), beta({3}, 0.0);
  TensorD running_mean({3}, 0.0), running_var({3}, 1.0), out;
  int64_t batches = 0;
  PfnSaved<double> saved;
  EXPECT_THAT(error_message([&] {
                pfn_forward_train(TensorD({2, 4, 10}), TensorD({3, 9}), gamma, beta,
                                  kPfnNormOptions, running_mean, running_var, batches, out, saved);
              }),
              HasSubstr("pfn_forward_train: expected weight of shape (C, 10)"));
  EXPECT_THAT(error_message([&] {
                pfn_forward_eval(TensorD({2, 10}), TensorD({3, 10}), gamma, beta, running_mean,
                                 running_var, kPfnNormOptions, out);
              }),
              HasSubstr("expected input of shape (P, N, D)"));
  TensorD d_input, d_weight, d_gamma, d_beta;
  EXPECT_THAT(error_message([&] {
                pfn_backward(TensorD({2, 3}), TensorD({2, 4, 10}), TensorD({3, 10}), gamma, saved,
                             d_input, d_weight, d_gamma, d_beta);
              }),
              HasSubstr("saved.max_slot"));
}

// ---------------------------------------------------------------- scatter

namespace {

// P distinct random cells of a (batch, height, width) canvas.
Tensor<int32_t> random_cells(int64_t pillars, int64_t batch, int64_t height, int64_t width,
                             Rng& rng) {
  std::vector<int32_t> all(static_cast<size_t>(batch * height * width));
  for (size_t i = 0; i < all.size(); ++i) all[i] = static_cast<int32_t>(i);
  rng.shuffle(all.begin(), all.end());
  Tensor<int32_t> cells({pillars, 3});
  for (int64_t p = 0; p < pillars; ++p) {
    const int32_t i = all[static_cast<size_t>(p)];
    cells(p, 0) = static_cast<int32_t>(i / (height * width));
    cells(p, 1) = static_cast<int32_t>(i / width % height);
    cells(p, 2) = static_cast<int32_t>(i % width);
  }
  return cells;
}

}  // namespace

TEST(HostScatter, PlacesFeaturesAndZerosElsewhere) {
  Rng rng(40);
  const Tensor<int32_t> cells = random_cells(7, 2, 5, 3, rng);
  const TensorD features = random_tensor({7, 3}, rng, 1, 2);  // nonzero
  TensorD canvas;
  scatter_forward(features, cells, 2, 5, 3, canvas);
  ASSERT_EQ(canvas.shape(), (Shape{2, 3, 5, 3}));
  TensorD expected({2, 3, 5, 3});
  for (int64_t p = 0; p < 7; ++p) {
    for (int64_t c = 0; c < 3; ++c)
      expected(cells(p, 0), c, cells(p, 1), cells(p, 2)) = features(p, c);
  }
  EXPECT_TRUE(test::all_close(canvas, expected, 0, 0));
}

TEST(HostScatter, GatherIsTheAdjointAndInvertsScatter) {
  Rng rng(41);
  const Tensor<int32_t> cells = random_cells(7, 2, 5, 3, rng);
  const TensorD features = random_tensor({7, 3}, rng);
  const TensorD d_canvas = random_tensor({2, 3, 5, 3}, rng);
  TensorD canvas, gathered, d_features;
  scatter_forward(features, cells, 2, 5, 3, canvas);
  scatter_backward(canvas, cells, gathered);
  EXPECT_TRUE(test::all_close(gathered, features, 0, 0));
  // <scatter(f), g> = <f, gather(g)>: the backward is the transpose of the forward.
  scatter_backward(d_canvas, cells, d_features);
  EXPECT_NEAR(dot(canvas, d_canvas), dot(features, d_features), 1e-12);

  TensorF canvas_f, gathered_f;
  scatter_forward(tensor_cast<float>(features), cells, 2, 5, 3, canvas_f);
  scatter_backward(canvas_f, cells, gathered_f);
  EXPECT_TRUE(test::all_close(gathered_f, tensor_cast<float>(features), 0, 0));
}

TEST(HostScatter, NoPillarsGiveAnEmptyCanvas) {
  const TensorD features({0, 3});
  const Tensor<int32_t> cells({0, 3});
  TensorD canvas({1}, 5.0), d_features;
  scatter_forward(features, cells, 2, 5, 3, canvas);
  EXPECT_TRUE(test::all_close(canvas, TensorD({2, 3, 5, 3}, 0.0), 0, 0));
  scatter_backward(canvas, cells, d_features);
  EXPECT_EQ(d_features.shape(), (Shape{0, 3}));
}

TEST(HostScatter, RejectsDuplicateAndOutOfRangeCells) {
  const TensorD features({2, 3}, 1.0);
  TensorD canvas;
  auto scatter = [&](std::vector<int32_t> a, std::vector<int32_t> b) {
    Tensor<int32_t> cells({2, 3});
    for (int i = 0; i < 3; ++i) cells(0, i) = a[i], cells(1, i) = b[i];
    return error_message([&] { scatter_forward(features, cells, 2, 5, 3, canvas); });
  };
  EXPECT_EQ(scatter({0, 1, 2}, {1, 1, 2}), "");  // same cell, other batch item
  EXPECT_THAT(scatter({0, 1, 2}, {0, 1, 2}),
              HasSubstr("pillars 0 and 1 have the same cell (batch 0, iy 1, ix 2)"));
  EXPECT_THAT(scatter({0, 1, 2}, {2, 1, 2}), HasSubstr("outside the canvas"));
  EXPECT_THAT(scatter({0, 5, 2}, {0, 1, 2}), HasSubstr("outside the canvas"));
  EXPECT_THAT(scatter({0, 1, -1}, {0, 1, 2}), HasSubstr("outside the canvas"));
  EXPECT_THAT(scatter({0, 1, 3}, {0, 1, 2}), HasSubstr("outside the canvas"));
  EXPECT_THAT(error_message([&] {
                scatter_forward(TensorD({3, 3}), Tensor<int32_t>({2, 3}), 2, 5, 3, canvas);
              }),
              HasSubstr("expected features of shape (P, C) with P = 2"));
  EXPECT_THAT(error_message([&] {
                scatter_forward(features, Tensor<int32_t>({2, 2}), 2, 5, 3, canvas);
              }),
              HasSubstr("expected cells of shape (P, 3)"));
  TensorD d_features;
  Tensor<int32_t> duplicate({2, 3});
  EXPECT_THAT(error_message([&] {
                scatter_backward(TensorD({2, 3, 5, 3}), duplicate, d_features);
              }),
              HasSubstr("scatter_backward: pillars 0 and 1 have the same cell"));
}
