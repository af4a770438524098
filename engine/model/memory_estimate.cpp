// The memory estimate and index limits of engine/model/memory_estimate.hpp. The channel widths
// follow the PillarSegNet constructor (engine/model/pillarsegnet.cpp); every size is computed in
// checked 64-bit arithmetic, so that an absurd config is an error saying so, not a wrapped number.
#include "engine/model/memory_estimate.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <initializer_list>
#include <string>
#include <utility>
#include <vector>

#include "core/error.hpp"

namespace pillarseg {

namespace {

constexpr int64_t kFloat = 4;

// One level of the U-Net: its cells and the channels of its tensors.
struct Level {
  int64_t cells = 0;    // H / 2^l x W / 2^l (floored level by level, as MaxPool)
  int64_t skip = 0;     // c_l: the Down block's output (level 0: the input canvas)
  int64_t down_in = 0;  // the Down block's input channels, pooled from the level above (l >= 1)
  // The Up block whose output is at this level: its input (at level l + 1), the upsampled
  // channels, the concatenation, the middle and output widths.
  int64_t up_in = 0, up = 0, cat = 0, mid = 0, out = 0;
};

// The U-Net of `config`, as the PillarSegNet constructor declares it.
std::vector<Level> unet_levels(const ModelConfig& config) {
  const int depth = config.depth;
  const int64_t b = config.base_width;
  std::vector<int64_t> c(static_cast<size_t>(depth) + 1);
  c[0] = config.input_channels();
  for (int i = 1; i <= depth; ++i) c[static_cast<size_t>(i)] = b << i;
  if (!config.transposed && depth >= 2)
    c[static_cast<size_t>(depth)] = c[static_cast<size_t>(depth) - 1];
  if (!config.transposed && depth == 1) c[1] = b;
  std::vector<Level> levels(static_cast<size_t>(depth) + 1);
  int64_t h = config.grid.height(), w = config.grid.width();
  for (int l = 0; l <= depth; ++l) {
    Level& level = levels[static_cast<size_t>(l)];
    level.cells = h * w;
    level.skip = c[static_cast<size_t>(l)];
    if (l >= 1) level.down_in = c[static_cast<size_t>(l) - 1];
    h /= 2, w /= 2;
  }
  int64_t current = c[static_cast<size_t>(depth)];
  for (int l = depth - 1; l >= 0; --l) {
    Level& level = levels[static_cast<size_t>(l)];
    level.up_in = current;
    level.up = config.transposed ? current / 2 : current;
    level.cat = level.skip + level.up;
    level.out =
        l == 0 ? b
               : (config.transposed ? c[static_cast<size_t>(l)] : c[static_cast<size_t>(l)] / 2);
    level.mid = config.transposed ? level.out : level.cat / 2;
    current = level.out;
  }
  return levels;
}

// Checked arithmetic on the sizes of one estimate, every error naming it.
class Sizes {
 public:
  explicit Sizes(std::string what) : what_(std::move(what)) {}
  uint64_t mul(std::initializer_list<int64_t> factors) const {
    return checked_product(factors, what_);
  }
  uint64_t add(uint64_t a, uint64_t b) const { return checked_sum({a, b}, what_); }
  uint64_t scale(uint64_t a, int64_t factor) const {
    uint64_t out = 0;
    PS_CHECK(factor >= 0 && !__builtin_mul_overflow(a, static_cast<uint64_t>(factor), &out),
             "{}: {} x {} overflows 64-bit arithmetic", what_, a, factor);
    return out;
  }
  const std::string& what() const { return what_; }

 private:
  std::string what_;
};

// Values of the trainable parameters and of the BatchNorm buffers.
struct ParameterCounts {
  uint64_t trainable = 0, buffers = 0;
};

ParameterCounts count_parameters(const ModelConfig& config, const std::vector<Level>& levels,
                                 const Sizes& s) {
  ParameterCounts n;
  const auto conv = [&](int64_t in, int64_t out, int64_t k, bool bias) {
    n.trainable =
        s.add(n.trainable, s.add(s.mul({out, in, k, k}), bias ? static_cast<uint64_t>(out) : 0));
  };
  const auto batchnorm = [&](int64_t channels) {
    n.trainable = s.add(n.trainable, s.mul({2, channels}));  // gamma, beta
    n.buffers = s.add(n.buffers, s.mul({2, channels}));      // running mean, variance
  };
  if (config.pillar_input) {
    conv(10, config.pillar_channels, 1, false);
    batchnorm(config.pillar_channels);
  }
  if (config.occupancy != OccupancyInput::None) {
    conv(config.occupancy_input_channels(), config.occupancy_channels, 3, false);
    batchnorm(config.occupancy_channels);
  }
  const size_t depth = levels.size() - 1;
  for (size_t l = 1; l <= depth; ++l) {
    conv(levels[l].down_in, levels[l].skip, 3, true);
    batchnorm(levels[l].skip);
    conv(levels[l].skip, levels[l].skip, 3, true);
    batchnorm(levels[l].skip);
  }
  for (size_t l = 0; l < depth; ++l) {
    const Level& v = levels[l];
    if (config.transposed) conv(v.up_in, v.up, 2, true);
    conv(v.cat, v.mid, 3, true);
    batchnorm(v.mid);
    conv(v.mid, v.out, 3, true);
    batchnorm(v.out);
  }
  conv(config.base_width, config.num_classes, 1, true);
  return n;
}

// The pillar rows planned for a batch: model.max_pillars a sample (or one a cell, at most
// kTypicalScanPoints, with max_pillars 0), with the model's headroom of a quarter.
int64_t planned_pillar_rows(const ModelConfig& config, int batch, const Sizes& s) {
  const int64_t cells = config.grid.cells();
  const int64_t per_sample = config.max_pillars > 0 ? std::min<int64_t>(config.max_pillars, cells)
                                                    : std::min(cells, kTypicalScanPoints);
  const auto rows = static_cast<int64_t>(s.mul({per_sample, batch}));
  return std::max<int64_t>(rows + rows / 4, 1024);
}

}  // namespace

uint64_t ModelMemoryEstimate::total() const {
  return checked_sum({parameters, activations, pillars}, "the model's memory estimate");
}

std::string ModelMemoryEstimate::breakdown() const {
  return fmt::format("parameters {}, activations {}, pillar buffers {}", format_bytes(parameters),
                     format_bytes(activations), format_bytes(pillars));
}

ModelMemoryEstimate estimate_model_memory(const ModelConfig& config, int batch, bool training) {
  const Sizes s(fmt::format("the memory of {} on a {} x {} grid, batch {}",
                            training ? "training" : "evaluation", config.grid.width(),
                            config.grid.height(), batch));
  PS_CHECK(batch >= 1, "{}: the batch size must be >= 1", s.what());
  const std::vector<Level> levels = unet_levels(config);
  const size_t depth = levels.size() - 1;
  const Level& top = levels[0];
  ModelMemoryEstimate e;

  const ParameterCounts params = count_parameters(config, levels, s);
  // Training: values, gradients and Adam's two moments of every trainable value.
  e.parameters = s.mul({kFloat, static_cast<int64_t>(s.add(
                                    s.scale(params.trainable, training ? 4 : 1), params.buffers))});

  if (config.pillar_input) {
    const int64_t rows = planned_pillar_rows(config, batch, s);
    const int64_t N = config.max_points_per_pillar, C = config.pillar_channels;
    // A row: N decorated points (10 floats), its cell (3 int32) and the PFN's output (C).
    int64_t row = N * 10 + 3 + C;
    // Training: the PFN's arg-max (C int32) and the output's gradient (the backends keep no
    // (N, C) working memory a pillar: they recompute the linear output per block).
    if (training) row += C + C;
    e.pillars = s.mul({kFloat, row, rows});
  }

  const int64_t K = config.num_classes;
  const int64_t occupancy_in = config.occupancy_input_channels();
  const int64_t occupancy_out =
      config.occupancy != OccupancyInput::None ? config.occupancy_channels : 0;
  const int64_t grid_map = config.grid_map_input ? 6 : 0;
  // Floats a sample holds: the labels and the predicted class ids, a byte a cell each (counted
  // as a float: upper), and the U-Net's tensors.
  uint64_t per_sample = top.cells;
  if (!training) {
    // Evaluation: the largest set alive at once. The inputs, with the pillar buffers: the canvas,
    // the input maps, the occupancy stream's output.
    uint64_t peak = s.mul({top.skip + occupancy_in + occupancy_out + grid_map, top.cells});
    const uint64_t inputs = peak;
    // Down block l reads level l - 1 (alive with every finer skip) and writes the pooled map, its
    // arg-max and the two convolutions' outputs.
    uint64_t finer_skips = 0;  // the skips of levels < l, read later by the decoder
    for (size_t l = 1; l <= depth; ++l) {
      finer_skips = s.add(finer_skips, s.mul({levels[l - 1].skip, levels[l - 1].cells}));
      const Level& v = levels[l];
      peak = std::max(peak, s.add(finer_skips, s.mul({2 * v.down_in + 2 * v.skip, v.cells})));
    }
    // Up block at level l: its input (level l + 1), the skip, the upsampled map (inside the
    // concatenation at batch 1), the concatenation, and the first convolution's output; the skips
    // of the finer levels stay alive.
    for (size_t l = 0; l < depth; ++l) {
      const Level& v = levels[l];
      uint64_t finer = 0;
      for (size_t k = 0; k < l; ++k) finer = s.add(finer, s.mul({levels[k].skip, levels[k].cells}));
      const int64_t working = std::max(v.skip + v.cat + (batch > 1 ? v.up : 0), v.cat + v.mid);
      peak = std::max(peak, s.add(finer, s.add(s.mul({working, v.cells}),
                                               s.mul({v.up_in, levels[l + 1].cells}))));
    }
    // The head and the outputs: the last Up block's output, the logits, their gradient and the
    // probabilities.
    peak = std::max(peak, s.mul({top.out + 3 * K, top.cells}));
    // The pillar buffers are dead once the canvas is scattered: in evaluation they share the
    // U-Net's memory, and the activations count only what the U-Net needs beyond them.
    const uint64_t labels = s.mul({kFloat, static_cast<int64_t>(per_sample), batch});
    const uint64_t unet = s.mul({kFloat, static_cast<int64_t>(peak), batch});
    const uint64_t at_inputs =
        s.add(s.mul({kFloat, static_cast<int64_t>(inputs), batch}), e.pillars);
    e.activations = s.add(labels, std::max(unet, at_inputs) - e.pillars);
    return e;
  }
  // What the backward reads is kept from the forward: the occupancy input and its stream's
  // convolution and BatchNorm outputs; a Down block's pooled map, arg-max and, per convolution,
  // its output and its BatchNorm's; an Up block's concatenation and two convolutions with their
  // BatchNorms; the logits and their gradient. (The canvas and the upsampled maps die at their
  // concatenations, the probabilities are written after the step.)
  uint64_t forward = s.mul({occupancy_in + 2 * occupancy_out + 2 * K, top.cells});
  for (size_t l = 1; l <= depth; ++l)
    forward = s.add(forward, s.mul({2 * levels[l].down_in + 4 * levels[l].skip, levels[l].cells}));
  for (size_t l = 0; l < depth; ++l) {
    const Level& v = levels[l];
    forward = s.add(forward, s.mul({v.cat + 2 * v.mid + 2 * v.out, v.cells}));
  }
  // The backward's gradients at their peak, in the last Up block: its concatenation's, split
  // into the canvas's and the upsampled map's (with the occupancy stream's then), while the
  // gradients of the coarser levels' outputs wait for their Down blocks' backward.
  uint64_t gradients = s.mul({top.cat + top.skip + top.up + occupancy_out, top.cells});
  for (size_t l = 1; l <= depth; ++l)
    gradients = s.add(gradients, s.mul({levels[l].skip, levels[l].cells}));
  per_sample = s.add(per_sample, s.add(forward, gradients));
  e.activations = s.mul({kFloat, static_cast<int64_t>(per_sample), batch});
  return e;
}

void check_model_memory(const ModelConfig& config, int batch, bool training,
                        const MemoryBudget& budget) {
  const ModelMemoryEstimate e = estimate_model_memory(config, batch, training);
  const uint64_t total = e.total();
  if (total <= budget.bytes) return;
  require_memory(total,
                 fmt::format("{} of PillarSegNet on a {} x {} grid of {} m cells (batch {})",
                             training ? "training" : "evaluation", config.grid.width(),
                             config.grid.height(), config.grid.cell, batch),
                 MemoryBudget{budget.bytes, fmt::format("{}; the estimate: {}", budget.description,
                                                        e.breakdown())});
}

void check_index_limits(const ModelConfig& config, int batch) {
  PS_CHECK(batch >= 1, "the batch size must be >= 1, got {}", batch);
  const int64_t W = config.grid.width(), H = config.grid.height();
  require_int32_count({W, H}, fmt::format("grid of {} x {} cells", W, H), "cell indices");
  if (!config.pillar_input) return;
  if (config.max_pillars > 0) {
    require_int32_count({config.max_pillars, batch},
                        fmt::format("model.max_pillars {} x batch {}", config.max_pillars, batch),
                        "pillar indices");
    require_int32_count({config.max_pillars, batch, config.max_points_per_pillar},
                        fmt::format("model.max_pillars {} x batch {} x {} points a pillar",
                                    config.max_pillars, batch, config.max_points_per_pillar),
                        "point rows of the PFN");
  } else {
    require_int32_count(
        {W, H, batch},
        fmt::format(
            "grid of {} x {} cells x batch {} (up to a pillar a cell with model.max_pillars 0)", W,
            H, batch),
        "pillar indices");
  }
}

}  // namespace pillarseg
