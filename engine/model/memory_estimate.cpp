// The memory estimate and index limits of engine/model/memory_estimate.hpp: the model's own
// parameters and op graph, planned; the sizes an absurd config could overflow are checked in
// 64-bit arithmetic first, so that it is an error saying so, not a wrapped number.
#include "engine/model/memory_estimate.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <initializer_list>
#include <string>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "engine/backend/backend.hpp"
#include "engine/model/model_graph.hpp"
#include "engine/model/parameters.hpp"

namespace pillarseg {

namespace {

// The pillar rows planned for a batch: model.max_pillars a sample (or one a cell, at most
// kTypicalScanPoints, with max_pillars 0), with the model's headroom.
int64_t planned_pillar_rows(const ModelConfig& config, int batch, const std::string& what) {
  const int64_t cells = config.grid.cells();
  const int64_t per_sample = config.max_pillars > 0 ? std::min<int64_t>(config.max_pillars, cells)
                                                    : std::min(cells, kTypicalScanPoints);
  const auto rows = static_cast<int64_t>(checked_product({per_sample, batch}, what));
  return pillar_capacity_for(rows, config.max_points_per_pillar);
}

}  // namespace

uint64_t ModelMemoryEstimate::total() const {
  return checked_sum({parameters, activations}, "the model's memory estimate");
}

std::string ModelMemoryEstimate::breakdown() const {
  return fmt::format("parameters {}, activations {} (pillar buffers {} of them)", format_bytes(parameters),
                     format_bytes(activations), format_bytes(pillars));
}

ModelMemoryEstimate estimate_model_memory(const ModelConfig& config, int batch, bool training) {
  const std::string what = fmt::format("the memory of {} on a {} x {} grid, batch {}",
                                       training ? "training" : "evaluation", config.grid.width(),
                                       config.grid.height(), batch);
  PS_CHECK(batch >= 1, "{}: the batch size must be >= 1", what);
  // The parameters, declared as the model declares them (nothing is allocated: the set is never
  // finalized; the backend only owns what a finalize would allocate).
  auto host = make_cpu_reference_backend();
  ParameterSet ps(*host);
  const Modules modules = declare_modules(config, ps);
  uint64_t trainable = 0, buffers = 0;
  int64_t widest = std::max<int64_t>({config.input_channels(), config.num_classes, config.pillar_channels,
                                      config.occupancy_input_channels()});
  for (const ParamEntry& e : ps.entries()) {
    (e.trainable ? trainable : buffers) += checked_product({shape_numel(e.shape)}, what);
    for (int64_t d : e.shape) widest = std::max(widest, d);
  }
  ModelMemoryEstimate e;
  // Training: values, gradients and Adam's two moments of every trainable value.
  e.parameters = checked_product(
      {4, static_cast<int64_t>(checked_sum({checked_product({static_cast<int64_t>(trainable), training ? 4 : 1}, what),
                                            buffers},
                                           what))},
      what);
  // The largest tensor any graph of this config can hold fits 64-bit arithmetic (the graph's
  // shapes and the planner's offsets are plain products).
  const int64_t rows = config.pillar_input ? planned_pillar_rows(config, batch, what) : 0;
  checked_product({config.grid.height(), config.grid.width(), batch, widest, 4, 16}, what);
  checked_product({std::max<int64_t>(rows, 1), config.max_points_per_pillar, 10, 4, 16}, what);
  // The activations: the graph the model would plan, in FP32 (16-bit activations only make it
  // smaller), with its pillar buffers at the rows above.
  ModelGraph g;
  build_model_graph(g, config, modules, ps, /*backend=*/nullptr, batch, training, Precision::F32, rows);
  e.activations = g.graph.plan();
  for (const GraphTensor& t : g.graph.tensors())
    if (t.dynamic_rows && t.planned()) e.pillars += t.bytes();
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
