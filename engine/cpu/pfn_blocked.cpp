// The CPU backend's PFN per block of pillars (see pfn_blocked.hpp); the spec is host/pfn.cpp.
#include "engine/cpu/pfn_blocked.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "core/eigen.hpp"
#include "core/ops.hpp"
#include "core/parallel.hpp"

namespace pillarseg::cpu {

namespace {

using RowMatrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using Points = Eigen::Map<const RowMatrix>;

// Pillars per block: 32 N rows of z, 160 KB at N = 20 and C = 64, stay in a core's L2 cache.
constexpr int64_t kPillarsPerBlock = 32;

struct PfnDims {
  int64_t pillars, slots, channels;
  int64_t rows() const { return pillars * slots; }
  int64_t blocks() const { return (pillars + kPillarsPerBlock - 1) / kPillarsPerBlock; }
};

PfnDims check_dims(const char* op, const Ref& points, const Ref& weight, const Ref& out) {
  require_shape(op, "out", out, op::pfn(points.shape, weight.shape, op));
  return {points.dim(0), points.dim(1), weight.dim(0)};
}

void check_channels(const char* op, const BatchNormRefs& bn, int64_t channels, bool saved) {
  const Shape c{channels};
  require_shape(op, "gamma", bn.gamma, c);
  require_shape(op, "beta", bn.beta, c);
  if (saved) {
    require_shape(op, "save_mean", bn.save_mean, c);
    require_shape(op, "save_invstd", bn.save_invstd, c);
  }
}

// fn(block, p0, p1, x, z) for every block of pillars [p0, p1), in parallel: x (rows, 10) its
// points, z (rows, C) = x weight^T in a buffer of the calling thread (fn may overwrite it).
template <class Fn>
void for_each_block(const PfnDims& d, const Ref& points, const Ref& weight, Fn&& fn) {
  const Points w(weight.data, d.channels, 10);
  parallel_chunks(d.blocks(), [&](int64_t begin, int64_t end, int) {
    RowMatrix z;
    for (int64_t b = begin; b < end; ++b) {
      const int64_t p0 = b * kPillarsPerBlock, p1 = std::min(d.pillars, p0 + kPillarsPerBlock);
      const Points x(points.data + p0 * d.slots * 10, (p1 - p0) * d.slots, 10);
      z.noalias() = x * w.transpose();
      fn(b, p0, p1, x, z);
    }
  });
}

// The blocks' per-channel parts (blocks, C) added in block order.
Eigen::ArrayXd sum_in_block_order(const std::vector<double>& parts, int64_t blocks,
                                  int64_t channels) {
  Eigen::ArrayXd total = Eigen::ArrayXd::Zero(channels);
  for (int64_t b = 0; b < blocks; ++b)
    total += Eigen::Map<const Eigen::ArrayXd>(parts.data() + b * channels, channels);
  return total;
}

// Per block, sum over its rows r of value(z(r, c), c) per channel, in double; then in block order.
template <class Value>
Eigen::ArrayXd channel_sums(const PfnDims& d, const Ref& points, const Ref& weight, Value&& value) {
  std::vector<double> parts(static_cast<size_t>(d.blocks() * d.channels), 0.0);
  for_each_block(d, points, weight,
                 [&](int64_t b, int64_t, int64_t, const Points&, const RowMatrix& z) {
                   double* sums = parts.data() + b * d.channels;
                   for (Eigen::Index r = 0; r < z.rows(); ++r) {
                     const float* row = z.data() + r * d.channels;
                     for (int64_t c = 0; c < d.channels; ++c) sums[c] += value(row[c], c);
                   }
                 });
  return sum_in_block_order(parts, d.blocks(), d.channels);
}

// out(p, c) = max over the slots of act(z(p N + n, c), c) for the block's pillars [p0, p1), NaN
// winning (torch.max), and max_slot(p, c) = the first slot reaching it, or -1 where the max is not
// > 0 (no gradient passes there).
template <class Activation>
void max_over_slots(const PfnDims& d, int64_t p0, int64_t p1, const RowMatrix& z, Activation&& act,
                    float* out, int32_t* max_slot) {
  const int64_t C = d.channels;
  for (int64_t p = p0; p < p1; ++p) {
    const float* pillar = z.data() + (p - p0) * d.slots * C;
    float* best = out + p * C;
    int32_t* slot = max_slot + p * C;
    for (int64_t c = 0; c < C; ++c) {
      best[c] = act(pillar[c], c);
      slot[c] = 0;
    }
    for (int64_t n = 1; n < d.slots; ++n) {
      const float* row = pillar + n * C;
      for (int64_t c = 0; c < C; ++c) {
        const float a = act(row[c], c);
        if (a > best[c] || (std::isnan(a) && !std::isnan(best[c]))) {
          best[c] = a;
          slot[c] = static_cast<int32_t>(n);
        }
      }
    }
    for (int64_t c = 0; c < C; ++c)
      if (!(best[c] > 0.0f)) slot[c] = -1;
  }
}

}  // namespace

void pfn_forward_eval(const Ref& points, const Ref& weight, const BatchNormRefs& bn, Ref& out) {
  const PfnDims d = check_dims("pfn_forward", points, weight, out);
  check_channels("pfn_forward", bn, d.channels, false);
  // BatchNorm's running statistics folded into a scale and shift (in double, as host/batchnorm).
  std::vector<float> scale(static_cast<size_t>(d.channels)), shift(static_cast<size_t>(d.channels));
  for (int64_t c = 0; c < d.channels; ++c) {
    const double s =
        bn.gamma.data[c] / std::sqrt(static_cast<double>(bn.running_var.data[c]) + bn.eps);
    scale[static_cast<size_t>(c)] = static_cast<float>(s);
    shift[static_cast<size_t>(c)] =
        static_cast<float>(bn.beta.data[c] - bn.running_mean.data[c] * s);
  }
  for_each_block(
      d, points, weight, [&](int64_t, int64_t p0, int64_t p1, const Points&, const RowMatrix& z) {
        for (int64_t p = p0; p < p1; ++p) {
          float* best = out.data + p * d.channels;
          for (int64_t c = 0; c < d.channels; ++c) best[c] = 0.0f;  // relu: the max is at least 0
          for (int64_t n = 0; n < d.slots; ++n) {
            const float* row = z.data() + ((p - p0) * d.slots + n) * d.channels;
            for (int64_t c = 0; c < d.channels; ++c)
              best[c] = std::max(
                  best[c], row[c] * scale[static_cast<size_t>(c)] + shift[static_cast<size_t>(c)]);
          }
        }
      });
}

void pfn_forward_train(const Ref& points, const Ref& weight, BatchNormRefs& bn, IRef& argmax,
                       Ref& out) {
  const char* op = "pfn_forward";
  const PfnDims d = check_dims(op, points, weight, out);
  require_shape(op, "argmax", argmax, out.shape);
  check_channels(op, bn, d.channels, true);
  require_shape(op, "running_mean", bn.running_mean, {d.channels});
  require_shape(op, "running_var", bn.running_var, {d.channels});
  const int64_t C = d.channels;

  // The batch statistics as host/batchnorm.cpp takes them: the count, the sums and the squares
  // about the mean, each summed over the replicas in turn.
  double count = static_cast<double>(d.rows());
  if (bn.replicas) bn.replicas->sum(&count, 1);
  PS_CHECK(count != 1, "{}: expected more than 1 value per channel when training, given points {}",
           op, shape_str(points.shape));
  Eigen::ArrayXd mean = Eigen::ArrayXd::Zero(C), variance = Eigen::ArrayXd::Zero(C);
  if (count > 0) {
    Eigen::ArrayXd sums =
        channel_sums(d, points, weight, [](float z, int64_t) { return static_cast<double>(z); });
    if (bn.replicas) bn.replicas->sum(sums.data(), C);
    mean = sums / count;
    sums = channel_sums(d, points, weight, [&](float z, int64_t c) {
      const double centred = static_cast<double>(z) - mean[c];
      return centred * centred;
    });
    if (bn.replicas) bn.replicas->sum(sums.data(), C);
    variance = sums / count;
    const double m = bn.momentum;
    for (int64_t c = 0; c < C; ++c) {
      bn.running_mean.data[c] = static_cast<float>((1 - m) * bn.running_mean.data[c] + m * mean[c]);
      bn.running_var.data[c] = static_cast<float>((1 - m) * bn.running_var.data[c] +
                                                  m * (variance[c] * (count / (count - 1))));
    }
  }
  const Eigen::ArrayXd inv_std = (variance + static_cast<double>(bn.eps)).rsqrt();
  std::vector<float> center(static_cast<size_t>(C)), scale(static_cast<size_t>(C));
  for (int64_t c = 0; c < C; ++c) {
    bn.save_mean.data[c] = center[static_cast<size_t>(c)] = static_cast<float>(mean[c]);
    bn.save_invstd.data[c] = static_cast<float>(inv_std[c]);
    scale[static_cast<size_t>(c)] =
        static_cast<float>(static_cast<double>(bn.gamma.data[c]) * inv_std[c]);
  }
  const auto act = [&](float z, int64_t c) {
    const auto k = static_cast<size_t>(c);
    const float a = (z - center[k]) * scale[k] + bn.beta.data[c];
    return a < 0.0f ? 0.0f : a;  // NaN passes the ReLU
  };
  for_each_block(d, points, weight,
                 [&](int64_t, int64_t p0, int64_t p1, const Points&, const RowMatrix& z) {
                   max_over_slots(d, p0, p1, z, act, out.data, argmax.data);
                 });
}

void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn, const IRef& argmax,
                  const Ref& dout, Ref& dweight, Ref& dgamma, Ref& dbeta) {
  const char* op = "pfn_backward";
  const PfnDims d = check_dims(op, points, weight, dout);
  require_shape(op, "argmax", argmax, dout.shape);
  require_shape(op, "dweight", dweight, weight.shape);
  require_shape(op, "dgamma", dgamma, {d.channels});
  require_shape(op, "dbeta", dbeta, {d.channels});
  check_channels(op, bn, d.channels, true);
  const int64_t C = d.channels, N = d.slots, blocks = d.blocks();
  const float* mean = bn.save_mean.data;
  const float* inv_std = bn.save_invstd.data;
  const auto xhat = [&](float z, int64_t c) { return (z - mean[c]) * inv_std[c]; };

  // The routed rows' sums: g = dout(p, c) at row (p, argmax(p, c)) of every pillar's block.
  std::vector<double> g_parts(static_cast<size_t>(blocks * C), 0.0),
      g_xhat_parts(g_parts.size(), 0.0);
  // Per block, the first (p, c) whose argmax is no slot, p C + c, or -1.
  std::vector<int64_t> bad_slot(static_cast<size_t>(blocks), -1);
  for_each_block(d, points, weight,
                 [&](int64_t b, int64_t p0, int64_t p1, const Points&, const RowMatrix& z) {
                   double* sum_g = g_parts.data() + b * C;
                   double* sum_g_xhat = g_xhat_parts.data() + b * C;
                   for (int64_t p = p0; p < p1; ++p) {
                     for (int64_t c = 0; c < C; ++c) {
                       const int32_t slot = argmax.data[p * C + c];
                       if (slot < -1 || slot >= N) {
                         if (bad_slot[static_cast<size_t>(b)] < 0)
                           bad_slot[static_cast<size_t>(b)] = p * C + c;
                         continue;
                       }
                       if (slot < 0) continue;
                       const float g = dout.data[p * C + c];
                       sum_g[c] += g;
                       sum_g_xhat[c] += g * xhat(z((p - p0) * N + slot, c), c);
                     }
                   }
                 });
  for (int64_t i : bad_slot) {
    PS_CHECK(i < 0, "{}: argmax({}, {}) = {} is neither -1 nor a slot of N = {}", op, i / C, i % C,
             argmax.data[i], N);
  }
  Eigen::ArrayXd sums(2 * C + 1);
  sums << sum_in_block_order(g_parts, blocks, C), sum_in_block_order(g_xhat_parts, blocks, C),
      static_cast<double>(d.rows());
  for (int64_t c = 0; c < C; ++c) {  // this replica's own share of the parameter gradient
    dbeta.data[c] = static_cast<float>(sums[c]);
    dgamma.data[c] = static_cast<float>(sums[C + c]);
  }
  if (bn.replicas) bn.replicas->sum(sums.data(), sums.size());
  const double count = sums[2 * C];

  // dz = BatchNorm's input gradient of g, with the sums of all replicas; dweight = dz^T points.
  std::vector<float> mean_g(static_cast<size_t>(C)), mean_g_xhat(static_cast<size_t>(C)),
      scale(static_cast<size_t>(C));
  for (int64_t c = 0; c < C; ++c) {
    const auto k = static_cast<size_t>(c);
    mean_g[k] = count > 0 ? static_cast<float>(sums[c] / count) : 0.0f;
    mean_g_xhat[k] = count > 0 ? static_cast<float>(sums[C + c] / count) : 0.0f;
    scale[k] =
        static_cast<float>(static_cast<double>(bn.gamma.data[c]) * static_cast<double>(inv_std[c]));
  }
  std::vector<float> weight_parts(static_cast<size_t>(blocks * C * 10));
  for_each_block(
      d, points, weight, [&](int64_t b, int64_t p0, int64_t p1, const Points& x, RowMatrix& z) {
        for (int64_t p = p0; p < p1; ++p) {
          const int32_t* slots = argmax.data + p * C;
          const float* g = dout.data + p * C;
          for (int64_t n = 0; n < N; ++n) {
            float* row = z.data() + ((p - p0) * N + n) * C;
            for (int64_t c = 0; c < C; ++c) {
              const auto k = static_cast<size_t>(c);
              const float routed = slots[c] == n ? g[c] : 0.0f;
              row[c] = ((routed - mean_g[k]) - xhat(row[c], c) * mean_g_xhat[k]) * scale[k];
            }
          }
        }
        Eigen::Map<RowMatrix>(weight_parts.data() + b * C * 10, C, 10).noalias() =
            z.transpose() * x;
      });
  for (int64_t i = 0; i < C * 10; ++i) {
    double total = 0.0;
    for (int64_t b = 0; b < blocks; ++b) total += weight_parts[static_cast<size_t>(b * C * 10 + i)];
    dweight.data[i] = static_cast<float>(total);
  }
}

}  // namespace pillarseg::cpu
