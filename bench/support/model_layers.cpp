#include "bench/support/model_layers.hpp"

namespace pillarseg::bench {

// Level (0 = input resolution, i = after i poolings) of a U-Net parameter, from its name:
// downI runs at level I, upJ's convs at depth - J, upJ's transposed conv reads level depth-J+1,
// outc and the occupancy stream at 0.
namespace {

int level_of(const std::string& name, int depth) {
  const auto number_after = [&](const std::string& prefix) {
    return std::stoi(name.substr(prefix.size()));
  };
  if (name.rfind("segmentation_head.down", 0) == 0) return number_after("segmentation_head.down");
  if (name.rfind("segmentation_head.up", 0) == 0) {
    const int j = number_after("segmentation_head.up");
    return name.find(".up.weight") != std::string::npos ? depth - j + 1 : depth - j;
  }
  return 0;
}

}  // namespace

std::vector<Layer> forward_layers(const PillarSegNet& net, int batch, int64_t pillars) {
  const ModelConfig& c = net.config();
  std::vector<int64_t> hs{c.grid.height()}, ws{c.grid.width()};
  for (int i = 1; i <= c.depth; ++i) hs.push_back(hs.back() / 2), ws.push_back(ws.back() / 2);
  std::vector<Layer> layers;
  for (const ParamEntry& e : net.parameters().entries()) {
    if (!e.trainable) continue;
    Layer l;
    l.name = e.name.substr(0, e.name.rfind('.'));
    if (e.name == "vfe.pfn_layers.0.linear.weight") {
      l.kind = Layer::Kind::Linear;
      l.out = e.shape[0], l.in = e.shape[1], l.h = pillars * c.max_points_per_pillar;
    } else if (e.shape.size() == 4) {
      const size_t level = static_cast<size_t>(level_of(e.name, c.depth));
      const bool transposed = e.name.find(".up.weight") != std::string::npos;
      l.kind = transposed ? Layer::Kind::Transposed : Layer::Kind::Conv;
      l.batch = batch;
      l.in = transposed ? e.shape[0] : e.shape[1];
      l.out = transposed ? e.shape[1] : e.shape[0];
      l.k = e.shape[2], l.h = hs.at(level), l.w = ws.at(level);
    } else {
      continue;
    }
    layers.push_back(l);
  }
  return layers;
}

double total_flops(const std::vector<Layer>& layers) {
  double sum = 0.0;
  for (const Layer& l : layers) sum += l.flops();
  return sum;
}

}  // namespace pillarseg::bench
