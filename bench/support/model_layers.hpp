// The multiply-add layers of PillarSegNet's forward, read from a model's parameter shapes, and
// their FLOPs: 2 x the multiply-adds of every conv, transposed conv and linear layer.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "engine/model/pillarsegnet.hpp"

namespace pillarseg::bench {

// One multiply-add layer of a forward. conv: output (batch, out, h, w) with a k x k kernel;
// transposed (k = 2, stride 2): input (batch, in, h, w); linear: rows = h.
struct Layer {
  enum class Kind { Conv, Transposed, Linear } kind = Kind::Conv;
  std::string name;
  int64_t batch = 1, in = 0, out = 0, k = 1, h = 1, w = 1;

  double flops() const {
    const double macs = static_cast<double>(batch * in * out * k * k) * static_cast<double>(h * w);
    return 2.0 * macs;
  }
};

// Every conv, transposed conv and linear layer of the model's forward for `batch` samples and
// `pillars` pillars, read from its parameters: weights of rank 4 are convs (O, I, k, k) or,
// named up.weight, transposed convs (I, O, 2, 2); the PFN's linear weight is (C, 10).
std::vector<Layer> forward_layers(const PillarSegNet& net, int batch, int64_t pillars);

double total_flops(const std::vector<Layer>& layers);

}  // namespace pillarseg::bench
