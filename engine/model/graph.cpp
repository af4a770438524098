#include "engine/model/graph.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <limits>
#include <numeric>

#include "core/error.hpp"

namespace pillarseg {

namespace {
constexpr size_t kAlignment = 64;
constexpr int kAlive = std::numeric_limits<int>::max();  // an output's last node
size_t aligned(size_t bytes) {
  return (bytes + kAlignment - 1) / kAlignment * kAlignment;
}
}  // namespace

int Graph::tensor(std::string name, Shape shape, DType dtype) {
  GraphTensor t;
  t.name = std::move(name);
  t.shape = std::move(shape);
  t.dtype = dtype;
  tensors_.push_back(std::move(t));
  return static_cast<int>(tensors_.size()) - 1;
}

int Graph::view(std::string name, int of, Shape shape, size_t byte_offset) {
  const GraphTensor& base = at(of);
  GraphTensor t;
  t.name = std::move(name);
  t.shape = std::move(shape);
  t.dtype = base.dtype;
  t.view_of = of;
  t.view_offset = byte_offset;
  PS_CHECK(byte_offset + t.bytes() <= base.bytes(),
           "graph: view {} ({} bytes at {}) outside {} ({} bytes)", t.name, t.bytes(), byte_offset,
           base.name, base.bytes());
  tensors_.push_back(std::move(t));
  return static_cast<int>(tensors_.size()) - 1;
}

int Graph::parameter(int index, Shape shape, bool gradient) {
  GraphTensor t;
  t.name = gradient ? "grad" : "param";
  t.shape = std::move(shape);
  t.parameter = index;
  t.gradient = gradient;
  tensors_.push_back(std::move(t));
  return static_cast<int>(tensors_.size()) - 1;
}

GraphNode& Graph::add(GraphNode node) {
  if (!node.args.empty()) {
    const OpRecord& record = op_record(node.op);
    PS_CHECK(node.reads.empty() && node.writes.empty(), "graph: node {} names its reads and writes (the record does)",
             node.name);
    PS_CHECK(node.args.size() == record.args.size(), "graph: node {} ({}) has {} arguments, the op takes {}",
             node.name, record.name, node.args.size(), record.args.size());
    for (size_t k = 0; k < node.args.size(); ++k) {
      const ArgSpec& spec = record.args[k];
      const int id = node.args[k];
      if (id < 0) {
        PS_CHECK(spec.optional, "graph: node {} ({}) lacks its argument {}", node.name, record.name, spec.name);
        continue;
      }
      PS_CHECK(id < static_cast<int>(tensors_.size()), "graph: node {} names tensor {} of {}", node.name, id,
               tensors_.size());
      PS_CHECK((spec.dtypes & dtypes_of(at(id).dtype)) != 0, "graph: node {} ({}): argument {} ({}) is {}",
               node.name, record.name, spec.name, at(id).name, dtype_name(at(id).dtype));
      if (spec.access != Access::Write) node.reads.push_back(id);
      if (spec.access != Access::Read) node.writes.push_back(id);
    }
    if (record.check) record.check(*this, node);
    node.flops = record.flops ? record.flops(*this, node) : 0.0;
  }
  for (const std::vector<int>* list : {&node.reads, &node.writes})
    for (int id : *list)
      PS_CHECK(id >= 0 && id < static_cast<int>(tensors_.size()),
               "graph: node {} names tensor {} of {}", node.name, id, tensors_.size());
  nodes_.push_back(std::move(node));
  return nodes_.back();
}

int Graph::root(int id) const {
  while (at(id).view_of >= 0) id = at(id).view_of;
  return id;
}

size_t Graph::plan() {
  const size_t n = tensors_.size();
  lifetimes_.assign(n, {kAlive, -1});
  for (size_t i = 0; i < nodes_.size(); ++i) {
    for (const std::vector<int>* list : {&nodes_[i].reads, &nodes_[i].writes}) {
      for (int id : *list) {
        std::pair<int, int>& life = lifetimes_[static_cast<size_t>(root(id))];
        life.first = std::min(life.first, static_cast<int>(i));
        life.second = std::max(life.second, static_cast<int>(i));
      }
    }
  }
  // Inputs and outputs of views extend their roots'.
  for (size_t id = 0; id < n; ++id) {
    const GraphTensor& t = tensors_[id];
    std::pair<int, int>& life = lifetimes_[static_cast<size_t>(root(static_cast<int>(id)))];
    if (t.input || t.persistent) life.first = -1;
    if (t.output || t.persistent) life.second = kAlive;
  }
  std::vector<size_t> order;
  for (size_t id = 0; id < n; ++id) {
    if (!tensors_[id].planned()) continue;
    PS_CHECK(lifetimes_[id].second >= lifetimes_[id].first,
             "graph: tensor {} is planned but no node reads or writes it", tensors_[id].name);
    order.push_back(id);
  }
  // Largest first (ties: in order of declaration), each at the lowest aligned offset that meets
  // no placed tensor alive at the same time.
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    return aligned(tensors_[a].bytes()) > aligned(tensors_[b].bytes());
  });
  std::vector<size_t> placed;
  size_t total = 0;
  for (size_t id : order) {
    GraphTensor& t = tensors_[id];
    const size_t bytes = aligned(t.bytes());
    std::vector<std::pair<size_t, size_t>> busy;
    for (size_t other : placed) {
      const bool meet = lifetimes_[other].first <= lifetimes_[id].second &&
                        lifetimes_[id].first <= lifetimes_[other].second;
      if (meet)
        busy.push_back(
            {tensors_[other].offset, tensors_[other].offset + aligned(tensors_[other].bytes())});
    }
    std::sort(busy.begin(), busy.end());
    size_t offset = 0;
    for (const auto& [begin, end] : busy) {
      if (offset + bytes <= begin) break;
      offset = std::max(offset, end);
    }
    t.offset = offset;
    total = std::max(total, offset + bytes);
    placed.push_back(id);
  }
  planned_bytes_ = total;
  return total;
}

double Graph::flops(size_t begin, size_t end) const {
  double sum = 0;
  for (size_t i = begin; i < std::min(end, nodes_.size()); ++i) sum += nodes_[i].flops;
  return sum;
}

size_t Graph::tensor_bytes(int id, int64_t pillar_rows) const {
  const GraphTensor& t = at(id);
  Shape shape = t.shape;
  if (t.dynamic_rows && !shape.empty()) shape[0] = pillar_rows;
  return static_cast<size_t>(shape_numel(shape)) * dtype_bytes(t.dtype);
}

size_t Graph::node_bytes(size_t i, int64_t pillar_rows) const {
  const GraphNode& n = nodes_.at(i);
  if (!n.args.empty()) {
    const OpRecord& record = op_record(n.op);
    if (record.least_bytes) return record.least_bytes(*this, n, pillar_rows);
  }
  const auto bytes = [&](const std::vector<int>& ids) {
    std::vector<int> distinct = ids;
    std::sort(distinct.begin(), distinct.end());
    distinct.erase(std::unique(distinct.begin(), distinct.end()), distinct.end());
    size_t sum = 0;
    for (int id : distinct) sum += tensor_bytes(id, pillar_rows);
    return sum;
  };
  return bytes(n.reads) + bytes(n.writes);
}

std::vector<GradientBucket> Graph::gradient_buckets(const std::vector<int64_t>& offsets,
                                                    int64_t total, int64_t min_count) const {
  PS_CHECK(!nodes_.empty(), "graph: gradient buckets of an empty graph");
  if (min_count <= 0) return {{nodes_.size() - 1, 0, total}};
  // The last node writing each parameter's gradient.
  std::vector<int64_t> last(offsets.size(), -1);
  for (size_t i = 0; i < nodes_.size(); ++i)
    for (int id : nodes_[i].writes) {
      const GraphTensor& t = at(root(id));
      if (t.gradient && t.parameter >= 0)
        last.at(static_cast<size_t>(t.parameter)) = static_cast<int64_t>(i);
    }
  // Trainable parameters from the end of the array.
  std::vector<size_t> order;
  for (size_t p = 0; p < offsets.size(); ++p)
    if (offsets[p] >= 0) {
      PS_CHECK(last[p] >= 0, "graph: no node writes the gradient of parameter {}", p);
      order.push_back(p);
    }
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return offsets[a] > offsets[b]; });
  std::vector<GradientBucket> buckets;
  int64_t end = total;
  GradientBucket open{0, total, 0};
  for (size_t k = 0; k < order.size(); ++k) {
    const size_t p = order[k];
    open.after = std::max(open.after, static_cast<size_t>(last[p]));
    open.offset = k + 1 == order.size() ? 0 : offsets[p];
    open.count = end - open.offset;
    if (open.count >= min_count || k + 1 == order.size()) {
      buckets.push_back(open);
      end = open.offset;
      open = {0, end, 0};
    }
  }
  std::stable_sort(
      buckets.begin(), buckets.end(),
      [](const GradientBucket& a, const GradientBucket& b) { return a.after < b.after; });
  return buckets;
}

std::string Graph::memory_report(size_t largest) const {
  std::vector<size_t> order;
  for (size_t id = 0; id < tensors_.size(); ++id)
    if (tensors_[id].planned()) order.push_back(id);
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return tensors_[a].bytes() > tensors_[b].bytes(); });
  size_t sum = 0;
  for (size_t id : order) sum += aligned(tensors_[id].bytes());
  std::string report =
      fmt::format("{} planned tensors, {:.1f} MiB of them in a block of {:.1f} MiB ({} nodes)\n",
                  order.size(), static_cast<double>(sum) / (1 << 20),
                  static_cast<double>(planned_bytes_) / (1 << 20), nodes_.size());
  for (size_t k = 0; k < std::min(largest, order.size()); ++k) {
    const GraphTensor& t = tensors_[order[k]];
    const auto& [first, last] =
        lifetimes_.empty() ? std::pair<int, int>{0, 0} : lifetimes_[order[k]];
    report += fmt::format("  {:<32} {:<22} {:>4} {:>9.1f} MiB at {:>9.1f} MiB, nodes {}..{}\n",
                          t.name, shape_str(t.shape), dtype_name(t.dtype),
                          static_cast<double>(t.bytes()) / (1 << 20),
                          static_cast<double>(t.offset) / (1 << 20),
                          first < 0 ? std::string("input") : std::to_string(first),
                          last == kAlive ? std::string("end") : std::to_string(last));
  }
  return report;
}

}  // namespace pillarseg
