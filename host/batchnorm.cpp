// BatchNorm over channel axis 1 of (B, C, H, W) or (M, C), optionally fused with ReLU: training
// and evaluation forward, training backward. See batchnorm.hpp for the semantics. (B, C, H, W)
// runs ranges of channels on the threads, each channel whole on one thread, so the results are
// the same for any thread count.
#include "host/batchnorm.hpp"

#include "core/eigen.hpp"
#include "core/parallel.hpp"

namespace pillarseg::host {

namespace {

using Eigen::ArrayXd;
using Eigen::Dynamic;
template <class T>
using ChannelVector = Eigen::Array<T, Dynamic, 1>;

// A tensor with its channels on axis 1, seen as `count` blocks of shape (C, per_block) whose row
// c holds channel c. Both layouts are plain views of the row-major data:
//   (M, C):       one column-major (C, M) block (channels_last);
//   (B, C, H, W): B row-major (C, H * W) blocks, one per batch item.
struct ChannelBlocks {
  int64_t count = 0;
  int64_t channels = 0;
  int64_t per_block = 0;
  bool channels_last = false;
  int64_t block_stride = 0;  // values from one block to the next (channels * per_block, or more
                             // for a range of the channels)
  int64_t values_per_channel() const { return count * per_block; }
};

// Below this many values a parallel region costs more than it saves.
constexpr int64_t kMinParallelValues = int64_t{1} << 15;

// Calls fn(part, c0) for ranges of channels [c0, c0 + part.channels), in parallel, part the
// blocks of those channels (their data starts c0 * per_block values in). Each channel is
// computed whole by one thread, as it is serially, so the results do not depend on the thread
// count. A channels-last (M, C) tensor, whose channels interleave in memory, runs whole.
template <class Fn>
void for_channel_ranges(const ChannelBlocks& blocks, Fn&& fn) {
  if (blocks.channels_last || blocks.channels < 2 ||
      blocks.channels * blocks.values_per_channel() < kMinParallelValues) {
    fn(blocks, int64_t{0});
    return;
  }
  parallel_chunks(blocks.channels, [&](int64_t c0, int64_t c1, int) {
    ChannelBlocks part = blocks;
    part.channels = c1 - c0;
    fn(part, c0);
  });
}

template <int Order, class T>
using ConstBlock = Eigen::Map<const Eigen::Array<T, Dynamic, Dynamic, Order>>;
template <int Order, class T>
using MutableBlock = Eigen::Map<Eigen::Array<T, Dynamic, Dynamic, Order>>;

template <int Order, class T>
ConstBlock<Order, T> block(const T* data, const ChannelBlocks& blocks, int64_t b) {
  return {data + b * blocks.block_stride, blocks.channels, blocks.per_block};
}

template <int Order, class T>
MutableBlock<Order, T> block(T* data, const ChannelBlocks& blocks, int64_t b) {
  return {data + b * blocks.block_stride, blocks.channels, blocks.per_block};
}

template <class T>
ChannelBlocks channel_blocks(const Tensor<T>& x, const char* op) {
  const Shape& s = x.shape();
  if (s.size() == 2) return {1, s[1], s[0], true, s[0] * s[1]};
  PS_CHECK(s.size() == 4, "{}: expected x of shape (B, C, H, W) or (M, C), given {}", op,
           shape_str(s));
  return {s[0], s[1], s[2] * s[3], false, s[1] * s[2] * s[3]};
}

template <class T>
void check_channel_vector(const Tensor<T>& v, const char* name, const Tensor<T>& x,
                          int64_t channels, const char* op) {
  PS_CHECK(v.shape() == Shape{channels},
           "{}: expected {} of shape ({}) for x of shape {}, given {}", op, name, channels,
           shape_str(x.shape()), shape_str(v.shape()));
}

void check_options(const BatchNormOptions& options, const char* op) {
  PS_CHECK(options.eps > 0, "{}: expected eps > 0, given {}", op, options.eps);
  PS_CHECK(options.momentum >= 0 && options.momentum <= 1,
           "{}: expected momentum in [0, 1], given {}", op, options.momentum);
}

template <class T>
ArrayXd to_double(const Tensor<T>& v) {
  return Eigen::Map<const ChannelVector<T>>(v.data(), v.numel()).template cast<double>();
}

template <class T>
void store(const ArrayXd& values, Tensor<T>& v) {
  v.resize({values.size()});
  Eigen::Map<ChannelVector<T>>(v.data(), v.numel()) = values.cast<T>();
}

// Adds to sums(c) the sum of row c of a (C, n) block expression, in double. The block is read in
// memory order: row by row when row-major, column by column when column-major. (Eigen's
// rowwise().sum() walks a column-major expression row by row when it cannot vectorise it, as
// for a float -> double cast, which strides through memory C times.)
template <int Order, class BlockExpr>
void add_channel_sums(const BlockExpr& values, ArrayXd& sums) {
  if constexpr (Order == Eigen::RowMajor) {
    for (Eigen::Index c = 0; c < values.rows(); ++c) {
      sums[c] += values.row(c).template cast<double>().sum();
    }
  } else {
    for (Eigen::Index j = 0; j < values.cols(); ++j) sums += values.col(j).template cast<double>();
  }
}

// Per-channel sums over all values of each channel, in double: of x, or of (x - mean)^2 when
// mean is given. Each channel is summed whole by one thread, in memory order.
template <int Order, class T>
void channel_sums(const T* x, const ChannelBlocks& blocks, const ArrayXd* mean, ArrayXd& sums) {
  for_channel_ranges(blocks, [&](const ChannelBlocks& part, int64_t c0) {
    ArrayXd part_sums = ArrayXd::Zero(part.channels);
    const T* px = x + c0 * part.per_block;
    for (int64_t b = 0; b < part.count; ++b) {
      if (mean) {
        const ArrayXd center = mean->segment(c0, part.channels);
        add_channel_sums<Order>(
            (block<Order>(px, part, b).template cast<double>().colwise() - center).square(),
            part_sums);
      } else {
        add_channel_sums<Order>(block<Order>(px, part, b), part_sums);
      }
    }
    sums.segment(c0, part.channels) = part_sums;
  });
}

template <class T>
void channel_sums(const T* x, const ChannelBlocks& blocks, const ArrayXd* mean, ArrayXd& sums) {
  if (blocks.channels_last) {
    channel_sums<Eigen::ColMajor>(x, blocks, mean, sums);
  } else {
    channel_sums<Eigen::RowMajor>(x, blocks, mean, sums);
  }
}

// sums over the replicas of a data-parallel run (synchronised BatchNorm), or as they are.
void sum_over_replicas(ReplicaSum* replicas, ArrayXd& sums) {
  if (replicas) replicas->sum(sums.data(), sums.size());
}

// The batch mean and biased variance of every channel, two-pass (the mean first, then the
// squares about it), over the values of all replicas. count: the values per channel of all of
// them.
template <class T>
void batch_statistics(const T* x, const ChannelBlocks& blocks, double count, ReplicaSum* replicas,
                      ArrayXd& mean, ArrayXd& variance) {
  ArrayXd sums(blocks.channels);
  channel_sums(x, blocks, nullptr, sums);
  sum_over_replicas(replicas, sums);
  mean = sums / count;
  channel_sums(x, blocks, &mean, sums);
  sum_over_replicas(replicas, sums);
  variance = sums / count;
}

// y = (x - center) * scale + shift per channel, then y = max(y, 0) when relu (written so that
// NaN passes). Centring first keeps float precision when |mean| is large against the spread.
template <int Order, class T>
void normalize_per_channel(const T* x, const ChannelBlocks& blocks, const ArrayXd& center,
                           const ArrayXd& scale, const ArrayXd& shift, bool relu, T* y) {
  for_channel_ranges(blocks, [&](const ChannelBlocks& part, int64_t c0) {
    const int64_t n = part.channels, offset = c0 * part.per_block;
    const ChannelVector<T> center_t = center.segment(c0, n).cast<T>();
    const ChannelVector<T> scale_t = scale.segment(c0, n).cast<T>();
    const ChannelVector<T> shift_t = shift.segment(c0, n).cast<T>();
    for (int64_t b = 0; b < part.count; ++b) {
      auto yb = block<Order>(y + offset, part, b);
      yb =
          ((block<Order>(x + offset, part, b).colwise() - center_t).colwise() * scale_t).colwise() +
          shift_t;
      if (relu) yb = (yb < T(0)).select(T(0), yb);
    }
  });
}

template <class T>
void normalize_per_channel(const Tensor<T>& x, const ChannelBlocks& blocks, const ArrayXd& center,
                           const ArrayXd& scale, const ArrayXd& shift, bool relu, Tensor<T>& y) {
  // In place (y is x, or a view of x's memory): every value is read before it is written; a
  // resize would zero x first.
  if (y.data() == x.data() && y.numel() > 0) {
    PS_CHECK(y.shape() == x.shape(), "batchnorm in place: y {} must have the shape of x {}",
             shape_str(y.shape()), shape_str(x.shape()));
  } else {
    y.resize_for_overwrite(x.shape());
  }
  if (blocks.channels_last) {
    normalize_per_channel<Eigen::ColMajor>(x.data(), blocks, center, scale, shift, relu, y.data());
  } else {
    normalize_per_channel<Eigen::RowMajor>(x.data(), blocks, center, scale, shift, relu, y.data());
  }
}

template <class T>
void forward_train(const char* op, const Tensor<T>& x, const Tensor<T>& gamma,
                   const Tensor<T>& beta, const BatchNormOptions& options, Tensor<T>& running_mean,
                   Tensor<T>& running_var, int64_t& num_batches_tracked, bool relu, Tensor<T>& y,
                   BatchNormSaved<T>& saved) {
  const ChannelBlocks blocks = channel_blocks(x, op);
  check_channel_vector(gamma, "gamma", x, blocks.channels, op);
  check_channel_vector(beta, "beta", x, blocks.channels, op);
  check_channel_vector(running_mean, "running_mean", x, blocks.channels, op);
  check_channel_vector(running_var, "running_var", x, blocks.channels, op);
  check_options(options, op);
  double counts = static_cast<double>(blocks.values_per_channel());
  if (options.replicas) options.replicas->sum(&counts, 1);
  const auto count = static_cast<int64_t>(counts);
  PS_CHECK(count != 1,
           "{}: expected more than 1 value per channel when training, given x of shape {}", op,
           shape_str(x.shape()));

  ArrayXd mean = ArrayXd::Zero(blocks.channels);
  ArrayXd variance = ArrayXd::Zero(blocks.channels);
  if (count > 0) {
    batch_statistics(x.data(), blocks, counts, options.replicas, mean, variance);
    const double m = options.momentum;
    const ArrayXd unbiased_variance = variance * (static_cast<double>(count) / (count - 1));
    store(((1 - m) * to_double(running_mean) + m * mean).eval(), running_mean);
    store(((1 - m) * to_double(running_var) + m * unbiased_variance).eval(), running_var);
  }
  ++num_batches_tracked;

  const ArrayXd inv_std = (variance + options.eps).rsqrt();
  normalize_per_channel(x, blocks, mean, to_double(gamma) * inv_std, to_double(beta), relu, y);
  store(mean, saved.mean);
  store(inv_std, saved.inv_std);
}

template <class T>
void forward_eval(const char* op, const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                  const Tensor<T>& running_mean, const Tensor<T>& running_var,
                  const BatchNormOptions& options, bool relu, Tensor<T>& y) {
  const ChannelBlocks blocks = channel_blocks(x, op);
  check_channel_vector(gamma, "gamma", x, blocks.channels, op);
  check_channel_vector(beta, "beta", x, blocks.channels, op);
  check_channel_vector(running_mean, "running_mean", x, blocks.channels, op);
  check_channel_vector(running_var, "running_var", x, blocks.channels, op);
  check_options(options, op);

  const ArrayXd scale = to_double(gamma) * (to_double(running_var) + options.eps).rsqrt();
  normalize_per_channel(x, blocks, to_double(running_mean), scale, to_double(beta), relu, y);
}

// With xhat = (x - mean) * inv_std and g = dy (masked by y > 0 after a ReLU), per channel over
// its n values (of all replicas, with synchronised BatchNorm):
//   dbeta = sum g,  dgamma = sum g * xhat,
//   dx = gamma * inv_std * (g - dbeta / n - xhat * dgamma / n).
// dgamma and dbeta are this replica's own sums (its share of the parameter gradient, which the
// trainer sums over the replicas with the others); dx takes those of all replicas.
// Pass 1: dx holds g, and the sums of g and g * xhat per channel.
template <int Order, class T>
void gradient_sums(const T* dy, const T* x, const T* relu_output, const ChannelBlocks& blocks,
                   const ArrayXd& mean, const ArrayXd& inv_std, T* dx, ArrayXd& sum_g,
                   ArrayXd& sum_g_xhat) {
  const ChannelVector<T> mean_t = mean.cast<T>();
  const ChannelVector<T> inv_std_t = inv_std.cast<T>();
  sum_g = ArrayXd::Zero(blocks.channels);
  sum_g_xhat = ArrayXd::Zero(blocks.channels);
  for (int64_t b = 0; b < blocks.count; ++b) {
    auto g = block<Order>(dx, blocks, b);
    const auto dyb = block<Order>(dy, blocks, b);
    if (relu_output) {
      g = (block<Order>(relu_output, blocks, b) > T(0)).select(dyb, T(0));
    } else {
      g = dyb;
    }
    const auto xb = block<Order>(x, blocks, b);
    add_channel_sums<Order>(g, sum_g);
    add_channel_sums<Order>(g * ((xb.colwise() - mean_t).colwise() * inv_std_t), sum_g_xhat);
  }
}

// Pass 2: dx from g in place, with the sums and the count of all replicas.
template <int Order, class T>
void input_gradient(const T* x, const ChannelBlocks& blocks, double count, const ArrayXd& gamma,
                    const ArrayXd& mean, const ArrayXd& inv_std, const ArrayXd& sum_g,
                    const ArrayXd& sum_g_xhat, T* dx) {
  const ChannelVector<T> mean_t = mean.cast<T>();
  const ChannelVector<T> inv_std_t = inv_std.cast<T>();
  const ChannelVector<T> mean_g = (sum_g / count).cast<T>();
  const ChannelVector<T> mean_g_xhat = (sum_g_xhat / count).cast<T>();
  const ChannelVector<T> scale = (gamma * inv_std).cast<T>();
  for (int64_t b = 0; b < blocks.count; ++b) {
    auto g = block<Order>(dx, blocks, b);
    const auto xb = block<Order>(x, blocks, b);
    const auto xhat = (xb.colwise() - mean_t).colwise() * inv_std_t;
    g = ((g.colwise() - mean_g) - xhat.colwise() * mean_g_xhat).colwise() * scale;
  }
}

template <int Order, class T>
void backward_blocks(const T* dy, const T* x, const T* relu_output, const ChannelBlocks& blocks,
                     const ArrayXd& gamma, const ArrayXd& mean, const ArrayXd& inv_std,
                     ReplicaSum* replicas, T* dx, ArrayXd& dgamma, ArrayXd& dbeta) {
  for_channel_ranges(blocks, [&](const ChannelBlocks& part, int64_t c0) {
    const int64_t n = part.channels, offset = c0 * part.per_block;
    ArrayXd part_dgamma, part_dbeta;
    gradient_sums<Order>(dy + offset, x + offset, relu_output ? relu_output + offset : nullptr,
                         part, mean.segment(c0, n), inv_std.segment(c0, n), dx + offset, part_dbeta,
                         part_dgamma);
    dgamma.segment(c0, n) = part_dgamma;
    dbeta.segment(c0, n) = part_dbeta;
  });
  double count = static_cast<double>(blocks.values_per_channel());
  ArrayXd sum_g = dbeta, sum_g_xhat = dgamma;
  if (replicas) {
    ArrayXd all(2 * blocks.channels + 1);
    all << dbeta, dgamma, count;
    replicas->sum(all.data(), all.size());
    sum_g = all.head(blocks.channels);
    sum_g_xhat = all.segment(blocks.channels, blocks.channels);
    count = all[2 * blocks.channels];
  }
  if (blocks.values_per_channel() == 0) return;
  for_channel_ranges(blocks, [&](const ChannelBlocks& part, int64_t c0) {
    const int64_t n = part.channels, offset = c0 * part.per_block;
    input_gradient<Order>(x + offset, part, count, gamma.segment(c0, n), mean.segment(c0, n),
                          inv_std.segment(c0, n), sum_g.segment(c0, n), sum_g_xhat.segment(c0, n),
                          dx + offset);
  });
}

template <class T>
void backward(const char* op, const Tensor<T>& dy, const Tensor<T>& x, const Tensor<T>* relu_output,
              const Tensor<T>& gamma, const BatchNormSaved<T>& saved, Tensor<T>& dx,
              Tensor<T>& dgamma, Tensor<T>& dbeta, ReplicaSum* replicas) {
  const ChannelBlocks blocks = channel_blocks(x, op);
  PS_CHECK(dy.shape() == x.shape(), "{}: expected dy of the shape of x {}, given {}", op,
           shape_str(x.shape()), shape_str(dy.shape()));
  if (relu_output) {
    PS_CHECK(relu_output->shape() == x.shape(), "{}: expected y of the shape of x {}, given {}", op,
             shape_str(x.shape()), shape_str(relu_output->shape()));
  }
  check_channel_vector(gamma, "gamma", x, blocks.channels, op);
  check_channel_vector(saved.mean, "saved.mean", x, blocks.channels, op);
  check_channel_vector(saved.inv_std, "saved.inv_std", x, blocks.channels, op);
  PS_CHECK(&dx != &x && &dx != relu_output, "{}: dx may replace dy but not x or y", op);

  if (&dx != &dy) dx.resize(x.shape());  // in place over dy: each dy is read before dx is written
  ArrayXd dgamma_d = ArrayXd::Zero(blocks.channels);
  ArrayXd dbeta_d = ArrayXd::Zero(blocks.channels);
  const T* relu_data = relu_output ? relu_output->data() : nullptr;
  if (blocks.values_per_channel() > 0 ||
      replicas) {  // every replica joins the sums, even with no values
    if (blocks.channels_last) {
      backward_blocks<Eigen::ColMajor>(dy.data(), x.data(), relu_data, blocks, to_double(gamma),
                                       to_double(saved.mean), to_double(saved.inv_std), replicas,
                                       dx.data(), dgamma_d, dbeta_d);
    } else {
      backward_blocks<Eigen::RowMajor>(dy.data(), x.data(), relu_data, blocks, to_double(gamma),
                                       to_double(saved.mean), to_double(saved.inv_std), replicas,
                                       dx.data(), dgamma_d, dbeta_d);
    }
  }
  store(dgamma_d, dgamma);
  store(dbeta_d, dbeta);
}

}  // namespace

template <class T>
void batchnorm_forward_train(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                             const BatchNormOptions& options, Tensor<T>& running_mean,
                             Tensor<T>& running_var, int64_t& num_batches_tracked, Tensor<T>& y,
                             BatchNormSaved<T>& saved) {
  forward_train("batchnorm_forward_train", x, gamma, beta, options, running_mean, running_var,
                num_batches_tracked, /*relu=*/false, y, saved);
}

template <class T>
void batchnorm_forward_eval(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                            const Tensor<T>& running_mean, const Tensor<T>& running_var,
                            const BatchNormOptions& options, Tensor<T>& y) {
  forward_eval("batchnorm_forward_eval", x, gamma, beta, running_mean, running_var, options,
               /*relu=*/false, y);
}

template <class T>
void batchnorm_backward(const Tensor<T>& dy, const Tensor<T>& x, const Tensor<T>& gamma,
                        const BatchNormSaved<T>& saved, Tensor<T>& dx, Tensor<T>& dgamma,
                        Tensor<T>& dbeta, ReplicaSum* replicas) {
  backward<T>("batchnorm_backward", dy, x, nullptr, gamma, saved, dx, dgamma, dbeta, replicas);
}

template <class T>
void batchnorm_relu_forward_train(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                                  const BatchNormOptions& options, Tensor<T>& running_mean,
                                  Tensor<T>& running_var, int64_t& num_batches_tracked,
                                  Tensor<T>& y, BatchNormSaved<T>& saved) {
  forward_train("batchnorm_relu_forward_train", x, gamma, beta, options, running_mean, running_var,
                num_batches_tracked, /*relu=*/true, y, saved);
}

template <class T>
void batchnorm_relu_forward_eval(const Tensor<T>& x, const Tensor<T>& gamma, const Tensor<T>& beta,
                                 const Tensor<T>& running_mean, const Tensor<T>& running_var,
                                 const BatchNormOptions& options, Tensor<T>& y) {
  forward_eval("batchnorm_relu_forward_eval", x, gamma, beta, running_mean, running_var, options,
               /*relu=*/true, y);
}

template <class T>
void batchnorm_relu_backward(const Tensor<T>& dy, const Tensor<T>& x, const Tensor<T>& y,
                             const Tensor<T>& gamma, const BatchNormSaved<T>& saved, Tensor<T>& dx,
                             Tensor<T>& dgamma, Tensor<T>& dbeta, ReplicaSum* replicas) {
  backward("batchnorm_relu_backward", dy, x, &y, gamma, saved, dx, dgamma, dbeta, replicas);
}

#define PILLARSEG_INSTANTIATE_BATCHNORM(T)                                                         \
  template void batchnorm_forward_train<T>(const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,   \
                                           const BatchNormOptions&, Tensor<T>&, Tensor<T>&,        \
                                           int64_t&, Tensor<T>&, BatchNormSaved<T>&);              \
  template void batchnorm_forward_eval<T>(const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,    \
                                          const Tensor<T>&, const Tensor<T>&,                      \
                                          const BatchNormOptions&, Tensor<T>&);                    \
  template void batchnorm_backward<T>(const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,        \
                                      const BatchNormSaved<T>&, Tensor<T>&, Tensor<T>&,            \
                                      Tensor<T>&, ReplicaSum*);                                    \
  template void batchnorm_relu_forward_train<T>(                                                   \
      const Tensor<T>&, const Tensor<T>&, const Tensor<T>&, const BatchNormOptions&, Tensor<T>&,   \
      Tensor<T>&, int64_t&, Tensor<T>&, BatchNormSaved<T>&);                                       \
  template void batchnorm_relu_forward_eval<T>(                                                    \
      const Tensor<T>&, const Tensor<T>&, const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,    \
      const BatchNormOptions&, Tensor<T>&);                                                        \
  template void batchnorm_relu_backward<T>(const Tensor<T>&, const Tensor<T>&, const Tensor<T>&,   \
                                           const Tensor<T>&, const BatchNormSaved<T>&, Tensor<T>&, \
                                           Tensor<T>&, Tensor<T>&, ReplicaSum*);

PILLARSEG_INSTANTIATE_BATCHNORM(float)
PILLARSEG_INSTANTIATE_BATCHNORM(double)

}  // namespace pillarseg::host
