// The multiply-add layers of PillarSegNet's forward and their FLOPs, read from the model's op
// graph (engine/model/model_graph.hpp): the graph's convolutions, transposed convolutions and PFN
// linear layer, each with the FLOPs of its op record, the ones `pillarseg bench --ops` adds up.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "engine/model/config.hpp"

namespace pillarseg::bench {

// One multiply-add layer of a forward. conv: output (batch, out, h, w) with a k x k kernel;
// transposed (k = 2, stride 2): input (batch, in, h, w); linear: rows = h. name: its weight's
// parameter name without ".weight".
struct Layer {
  enum class Kind { Conv, Transposed, Linear } kind = Kind::Conv;
  std::string name;
  int64_t batch = 1, in = 0, out = 0, k = 1, h = 1, w = 1;
  double flops = 0;  // the node's, from its op record: 2 x its multiply-adds
};

// Every conv, transposed conv and linear layer of the FP32 evaluation forward of `config`'s model
// for `batch` samples and `pillars` pillars, in the order the graph runs them.
std::vector<Layer> forward_layers(const ModelConfig& config, int batch, int64_t pillars);

double total_flops(const std::vector<Layer>& layers);

}  // namespace pillarseg::bench
