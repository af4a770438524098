#include "bench/support/model_layers.hpp"

#include <memory>
#include <string>

#include "engine/backend/backend.hpp"
#include "engine/model/model_graph.hpp"
#include "engine/model/op_record.hpp"
#include "engine/model/parameters.hpp"

namespace pillarseg::bench {

std::vector<Layer> forward_layers(const ModelConfig& config, int batch, int64_t pillars) {
  // The parameters as the model declares them (never finalized: nothing is allocated), and the
  // graph the model would run on them.
  const std::unique_ptr<Backend> host = make_cpu_reference_backend();
  ParameterSet ps(*host);
  const Modules modules = declare_modules(config, ps);
  ModelGraph g;
  build_model_graph(g, config, modules, ps, /*backend=*/nullptr, batch, /*training=*/false, Precision::F32,
                    pillars);
  const auto shape = [&](int id) -> const Shape& { return g.graph.at(id).shape; };
  const auto name_of = [&](int weight) {
    const std::string& name = ps.entries().at(static_cast<size_t>(g.graph.at(weight).parameter)).name;
    return name.substr(0, name.rfind('.'));
  };
  std::vector<Layer> layers;
  for (const GraphNode& n : g.graph.nodes()) {
    Layer l;
    l.flops = n.flops;
    if (n.op == OpKind::PfnForward) {
      const auto a = n.as<PfnForwardArgs>();
      const Shape &points = shape(a.points), &w = shape(a.w);  // (P, N, 10), (C, 10)
      l.kind = Layer::Kind::Linear, l.name = name_of(a.w);
      l.out = w[0], l.in = w[1], l.h = points[0] * points[1];
    } else if (n.op == OpKind::Conv2d || n.op == OpKind::Conv2dBnReluEval) {
      const auto a = n.as<Conv2dArgs>();
      const Shape &y = shape(a.y), &w = shape(a.w);  // (B, O, H, W), (O, I, k, k)
      l.kind = Layer::Kind::Conv, l.name = name_of(a.w);
      l.batch = y[0], l.out = w[0], l.in = w[1], l.k = w[2], l.h = y[2], l.w = y[3];
    } else if (n.op == OpKind::ConvTranspose2d) {
      const auto a = n.as<Conv2dArgs>();
      const Shape &x = shape(a.x), &w = shape(a.w);  // (B, I, H, W), (I, O, 2, 2)
      l.kind = Layer::Kind::Transposed, l.name = name_of(a.w);
      l.batch = x[0], l.in = w[0], l.out = w[1], l.k = w[2], l.h = x[2], l.w = x[3];
    } else {
      continue;
    }
    layers.push_back(l);
  }
  return layers;
}

double total_flops(const std::vector<Layer>& layers) {
  double sum = 0.0;
  for (const Layer& l : layers) sum += l.flops;
  return sum;
}

}  // namespace pillarseg::bench
