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
#include <string>
#include <utility>
#include <vector>

#include "core/tensor.hpp"

namespace pillarseg {

enum class DType { F32, I32, U8, U16 };  // U16: 16-bit floats (BF16, FP16) as bits
size_t dtype_bytes(DType dtype);
const char* dtype_name(DType dtype);

enum class OpKind {
  FillZero,          // w0 = 0
  PfnForward,        // r: points, weight | w: out (training: argmax, save stats)
  PfnBackward,       // r: points, weight, argmax, dout | w: dweight, dgamma, dbeta
  Scatter,           // r: features, cells | w: canvas band
  ScatterBackward,   // r: dcanvas band, cells | w: dfeatures
  CopyChannels,      // r: x | w: band of y
  ExtractChannels,   // r: band of y | w: x
  Conv2d,            // r: x, w, bias | w: y
  Conv2dBnReluEval,  // r: x, w, bias, BatchNorm | w: y
  Conv2dBackward,    // r: x, w, dy | w: dx, dw, dbias
  ConvTranspose2x2,  // r: x, w, bias | w: y
  ConvTranspose2x2Backward,
  BatchNormRelu,          // r: x | w: y (training: save stats)
  BatchNormReluBackward,  // r: x, y, dy, save stats | w: dx (may be dy), dgamma, dbeta
  MaxPool2x2,             // r: x | w: y, argmax
  MaxPool2x2Backward,     // r: dy, argmax | w: dx
  Upsample2x,
  Upsample2xBackward,
  PadConcat,          // r: skip, up | w: y
  PadConcatBackward,  // r: dy | w: dskip, dup
  AddInplace,         // r: a, b | w: a
  Loss,               // r: logits, labels, coefficients | w: dlogits
  // Mixed precision: 16-bit weights prepared from the FP32 parameters (in the evaluation forward
  // into persistent tensors, again only when the parameters changed), then the tensor-core
  // convolution.
  PrepareConvWeights,           // r: w, bias, BatchNorm | w: w16, bias_out, transformed
  PrepareConvTransposeWeights,  // r: w, bias | w: w16, bias_out
  Conv2dHalf,                   // r: x, w16, bias_out, transformed | w: y (relu: + ReLU)
  ConvTranspose2x2Half,         // r: x, w16, bias_out | w: y
  // Mixed precision (training): the gradients on the tensor cores from the FP32 tensors.
  Conv2dBackwardHalf,            // r: x, w, dy | w: dx, dw, dbias
  ConvTranspose2x2BackwardHalf,  // r: x, w, dy | w: dx, dw, dbias
  ToHalf,                        // r: x (FP32) | w: y (16-bit)
  MaxPool2x2Half,                // r: x | w: y (16-bit, no arg-max)
  Upsample2xHalf,                // r: x | w: y
  PadConcatHalf,                 // r: skip, up | w: y
  CopyChannelsHalf,              // r: x | w: band of y
  ScatterHalf,                   // r: features, cells | w: 16-bit canvas band
};
const char* op_name(OpKind op);

// Which part of a forward a node belongs to, for the stage timing of pillarseg bench.
enum class Stage { Pfn, Scatter, Occupancy, GridMap, UNet, Head, Loss, Backward };

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
  std::vector<int> args;  // the op's tensors in its Backend method's order (-1: absent)
  std::vector<int> reads, writes;
  int pad = 0;            // convolutions
  int channel0 = 0;       // scatter, channel copies
  int batchnorm = -1;     // the model's BatchNorm this node uses
  bool training = false;  // PFN, BatchNorm: batch statistics
  bool relu = false;      // Conv2dHalf
  Shape weight;           // Conv2dHalf, ConvTranspose2x2Half: the FP32 weight's shape
  double flops = 0;       // 2 x multiply-adds of its arithmetic on weights
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

  GraphNode& add(GraphNode node);
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
