// The model as one explicit list of ops (STYLE.md rule 14): a Graph holds tensors and nodes, each
// node an op of the Backend with the tensors it reads and writes and its output's shape from the
// op's shape function (core/ops.hpp). PillarSegNet builds one graph for the evaluation forward
// and one for the training step (forward, loss, backward); everything else reads these lists:
//   - the lifetime planner (plan()): every planned tensor lives from the first node that touches
//     it to the last (or to the end, for outputs; the whole graph, for persistent tensors such as
//     the evaluation's prepared 16-bit weights), and tensors whose lifetimes are disjoint share
//     bytes (greedy by size, lowest offset that overlaps no tensor alive at the same time); views
//     lie inside another tensor and share its lifetime; external tensors (parameters, gradients)
//     are bound by the model;
//   - graph capture (the model records the evaluation forward's nodes);
//   - FLOP and byte counts (flops(), node_bytes()) and per-op timing (the model's node timer)
//     for the benchmarks;
//   - the memory report (memory_report());
//   - the gradient buckets of data-parallel training (gradient_buckets()).
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "core/dtype.hpp"
#include "core/error.hpp"
#include "core/tensor.hpp"
#include "engine/model/op_record.hpp"

namespace pillarseg {

// Which part of a forward a node belongs to, for the stage timing of pillarseg bench.
enum class Stage { Pfn, Scatter, Occupancy, UNet, Head, Loss, Backward };

struct GraphTensor {
  std::string name;  // "down2.conv1.out": for the memory report
  Shape shape;
  DType dtype = DType::F32;
  int view_of = -1;  // >= 0: lies in that tensor at view_offset bytes
  size_t view_offset = 0;
  int parameter = -1;  // >= 0: a parameter's value, or its gradient with `gradient`
  bool gradient = false;
  bool input = false;         // written before the graph runs (an upload): alive from the start
  bool output = false;        // read after the graph ran: alive to the end
  bool persistent = false;    // kept from one run to the next: alive from the start to the end
  bool dynamic_rows = false;  // dim 0 is the pillar rows of the current batch (planned: capacity)
  size_t offset = 0;          // planned: bytes into the block
  size_t bytes() const { return static_cast<size_t>(shape_numel(shape)) * dtype_bytes(dtype); }
  bool planned() const { return view_of < 0 && parameter < 0; }
};

struct GraphNode {
  OpKind op = OpKind::FillZero;
  Stage stage = Stage::UNet;
  std::string name;       // "down2.conv1"
  std::vector<int> args;  // the op's tensors in its record's order (-1: absent)
  std::vector<int> reads, writes;  // from the record's accesses (Graph::add)
  int pad = 0;            // convolutions
  int channel0 = 0;       // scatter, channel copies
  int batchnorm = -1;     // the model's BatchNorm this node uses
  bool training = false;  // PFN, BatchNorm: batch statistics
  bool relu = false;      // PreparedConv2d
  Shape weight;           // PreparedConv2d, PreparedConvTranspose2d: the FP32 weight's shape
  // The arithmetic of a convolution's backward on FP32 tensors: F32, or BF16 / F16 on the
  // tensor cores (the prepared convolutions' is their prepared weights' dtype).
  DType compute = DType::F32;
  // INT8 convolutions: how the input is quantized, calibrated (engine/model/calibration.hpp).
  Int8Input int8_input;
  double flops = 0;       // from the record (Graph::add)

  // The arguments as the op's struct (engine/model/op_record.hpp).
  template <class Args>
  Args as() const {
    PS_CHECK(args.size() * sizeof(int) == sizeof(Args), "graph: node {} has {} arguments, its op {}", name,
             args.size(), sizeof(Args) / sizeof(int));
    Args a;
    std::memcpy(static_cast<void*>(&a), args.data(), sizeof(Args));
    return a;
  }
};

// A range of the flat parameter-gradient array, [offset, offset + count), that no node after
// node `after` writes: its sum over the replicas may begin there (DESIGN.md section 8).
struct GradientBucket {
  size_t after = 0;
  int64_t offset = 0, count = 0;
};

class Graph {
 public:
  // A planned activation (or an input, or an output), a view into one, or an external tensor.
  int tensor(std::string name, Shape shape, DType dtype = DType::F32);
  int view(std::string name, int of, Shape shape, size_t byte_offset = 0);
  int parameter(int index, Shape shape, bool gradient);
  GraphTensor& at(int id) { return tensors_.at(static_cast<size_t>(id)); }
  const GraphTensor& at(int id) const { return tensors_.at(static_cast<size_t>(id)); }
  const std::vector<GraphTensor>& tensors() const { return tensors_; }

  // A node of op n.op with n.args in its record's order: checks them against the record (count,
  // presence, dtypes, the shape rule) and sets reads, writes and flops from it. A node without
  // args keeps the reads and writes it was given (the planner's tests).
  GraphNode& add(GraphNode node);
  // The same from the op's argument struct; `attributes` carries the rest (stage, pad, ...).
  template <class Args>
  GraphNode& add(OpKind op, std::string name, const Args& args, GraphNode attributes = {}) {
    attributes.op = op;
    attributes.name = std::move(name);
    attributes.args = args_vector(args);
    return add(std::move(attributes));
  }
  const std::vector<GraphNode>& nodes() const { return nodes_; }
  size_t size() const { return nodes_.size(); }

  // Places every planned tensor (see the file comment); returns the bytes of the block.
  size_t plan();
  size_t planned_bytes() const { return planned_bytes_; }
  // After plan(): the first and last node that a planned tensor is alive at (-1: from before the
  // first node, an input; INT_MAX: to the end, an output).
  std::pair<int, int> lifetime(int id) const {
    return lifetimes_.at(static_cast<size_t>(root(id)));
  }
  double flops(size_t begin, size_t end) const;
  // The bytes node i must move at the least: every distinct tensor it reads, once, and every
  // one it writes, once (one it updates in place counts twice), at its dtype; but for the ops
  // that name a whole tensor of which they move a band or some rows (channel copies and
  // extractions, the scatter and its backward), that band's or those rows' bytes. Dim 0 of
  // dynamic-row tensors is `pillar_rows`.
  size_t node_bytes(size_t i, int64_t pillar_rows) const;
  // A tensor's bytes at its dtype, dim 0 of a dynamic-row tensor being `pillar_rows`.
  size_t tensor_bytes(int id, int64_t pillar_rows) const;
  // The largest planned tensors with their offsets and lifetimes, and the total, as text.
  std::string memory_report(size_t largest = 12) const;
  // The flat gradient array [0, total) cut into buckets for a sum overlapped with the backward.
  // offsets[i]: parameter i's first element in the array (-1: not trainable, not in it; any
  // padding after a parameter goes with it). Walking the parameters from the end of
  // the array (the backward meets the last layers first), each bucket gathers whole parameters
  // until it holds at least min_count elements (the last takes what is left); it is ready after
  // the last node writing any of its gradients. In the order they become ready (then from the
  // end of the array). min_count <= 0: one bucket, after the last node. Throws when a trainable
  // parameter's gradient is written by no node.
  std::vector<GradientBucket> gradient_buckets(const std::vector<int64_t>& offsets, int64_t total,
                                               int64_t min_count) const;

 private:
  int root(int id) const;
  std::vector<GraphTensor> tensors_;
  std::vector<GraphNode> nodes_;
  std::vector<std::pair<int, int>> lifetimes_;  // per tensor: first and last node (planned roots)
  size_t planned_bytes_ = 0;
};

}  // namespace pillarseg
