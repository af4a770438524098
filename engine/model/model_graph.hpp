// PillarSegNet's modules and its op graphs (DESIGN.md sections 2 and 7): declare_modules() adds
// every parameter of a config's model to a ParameterSet, in the order of the PyTorch state_dict
// (which the seeded initialisation follows); build_model_graph() emits the nodes of the
// evaluation forward or of the training step (forward, loss, backward) in the order a backend
// runs them, each through its op's record (engine/model/op_record.hpp). PillarSegNet plans and
// runs these graphs; the memory estimate (engine/model/memory_estimate.hpp) plans them without a
// model.
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "engine/backend/backend.hpp"
#include "engine/model/config.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/parameters.hpp"

namespace pillarseg {

// Conv2d parameters: weight (O, I, k, k), optional bias (O).
struct ConvParams {
  int weight = -1, bias = -1;
  int in = 0, out = 0, k = 3, pad = 1;
};

struct BnParams {
  int gamma = -1, beta = -1, mean = -1, var = -1;
  std::string counter;
  float eps = 1e-5f, momentum = 0.1f;
  float module_momentum = 0.1f;  // the PyTorch module's; `momentum` differs while recalibrating
};

// Conv -> BatchNorm -> ReLU; bn indexes the model's BatchNorm table.
struct ConvBnRelu {
  ConvParams conv;
  int bn = -1;
};

// [Conv3x3 (bias) -> BN -> ReLU] x 2, PyTorch module `double_conv` (indices 0,1 and 3,4).
struct DoubleConv {
  ConvBnRelu first, second;
};

// MaxPool 2x2 -> DoubleConv.
struct Down {
  DoubleConv conv;
  int in = 0, out = 0;
};

// Upsample (bilinear x2 or ConvTranspose 2x2/2) -> pad to the skip -> [skip, up] -> DoubleConv.
struct Up {
  DoubleConv conv;
  bool transposed = false;
  ConvParams up;  // transposed only: weight (in, in/2, 2, 2), bias (in/2)
  int in = 0, up_channels = 0, skip_channels = 0;
};

// Every module of a model: indices into its ParameterSet and BatchNorm table.
struct Modules {
  int pfn_weight = -1, pfn_bn = -1;
  ConvBnRelu occupancy;  // conv.weight < 0 without the occupancy stream
  std::vector<Down> downs;
  std::vector<Up> ups;
  ConvParams head;
  std::vector<BnParams> bns;
};

// Declares the parameters of `config`'s model into ps (before its finalize()).
Modules declare_modules(const ModelConfig& config, ParameterSet& ps);

// One graph of the model and the tensors the model binds outside its nodes.
struct ModelGraph {
  Graph graph;
  size_t forward_end = 0;  // nodes [0, forward_end) are the forward, then the loss node
  size_t loss_node = 0;
  int pillar_points = -1, pillar_cells = -1, occupancy_input = -1, grid_map_input = -1;
  int logits = -1, d_logits = -1, probs = -1, labels = -1, coefficients = -1, predicted = -1;
};

// The graph of the evaluation forward (training: the training step) for `batch` samples and
// pillar buffers of `pillar_capacity` rows, its convolutions in `precision` (the evaluation
// forward also keeps the U-Net's activations in it; INT8: in BF16, with the U-Net's inputs
// quantized as `int8_inputs` says by quantization_key, a missing one an error naming it); `backend` (may be
// null) gives its own transformed form of prepared weights where it has one.
void build_model_graph(ModelGraph& out, const ModelConfig& config, const Modules& modules, const ParameterSet& ps,
                       const Backend* backend, int batch, bool training, Precision precision,
                       int64_t pillar_capacity, const std::map<std::string, Int8Input>* int8_inputs = nullptr);

// A convolution's key for its INT8 scales: its weight's name without ".weight"
// ("segmentation_head.down1.maxpool_conv.1.double_conv.0").
std::string quantization_key(const std::string& weight_name);

// The rows the pillar buffers are planned for when a batch has `pillars`: with a quarter's
// headroom (so that a slowly rising count does not re-plan every batch), at least 1024, within the
// 32-bit point rows of the PFN.
int64_t pillar_capacity_for(int64_t pillars, int64_t points_per_pillar);

}  // namespace pillarseg
