// One record per op kind of the model's graphs (DESIGN.md section 7, STYLE.md rule 14): its
// arguments (names, whether the op reads or writes each, which dtypes each takes, which may be
// absent), its shape rule (core/ops.hpp, checked when a node is added to a graph), its FLOPs and
// least bytes, and the Backend call that runs it. Everything else derives from the record: a
// node's reads and writes (the planner's lifetimes), its FLOPs (the benchmarks), its bytes (the
// roofline), and the executor's dispatch.
//
// A node's arguments are one of the structs below, in the record's order: the builder emits
// `add_node(OpKind::Conv2d, name, Conv2dArgs{.x = x, .w = w, .bias = b, .y = y})`, the record's
// run function reads `a.x`; no argument position is written anywhere else. The dtype is the
// tensor's: a max-pool of BF16 activations is the MaxPool2d op on BF16 tensors, and a
// convolution's arithmetic (its 16-bit tensor-core kind) is that of its prepared weights or, for
// a backward that takes FP32 tensors, the node's `compute` dtype.
#pragma once

#include <bit>
#include <cstdint>
#include <string>
#include <vector>

#include "core/dtype.hpp"
#include "engine/backend/backend.hpp"

namespace pillarseg {

class Graph;
struct GraphNode;

enum class OpKind {
  FillZero,
  PfnForward,
  PfnBackward,
  Scatter,
  ScatterBackward,
  CopyChannels,
  ExtractChannels,
  Conv2d,
  Conv2dBnReluEval,
  Conv2dBackward,
  ConvTranspose2d,
  ConvTranspose2dBackward,
  BatchNormRelu,
  BatchNormReluBackward,
  MaxPool2d,
  MaxPool2dBackward,
  UpsampleBilinear,
  UpsampleBilinearBackward,
  PadConcat,
  PadConcatBackward,
  AddInplace,
  Loss,
  // The weights of a mixed-precision convolution, prepared from the FP32 parameters (BatchNorm
  // folded in for the evaluation) in the dtype of the prepared tensor, and the convolutions on
  // them.
  PrepareConvWeights,
  PrepareConvTransposeWeights,
  PreparedConv2d,
  PreparedConvTranspose2d,
  Convert,  // x -> y in y's dtype (FP32 -> BF16 / FP16, rounded to nearest even)
};

// The arguments of each op, in its record's order (-1: absent, where the record allows it).
struct FillZeroArgs { int y = -1; };
struct PfnForwardArgs { int points = -1, w = -1, argmax = -1, out = -1, save_mean = -1, save_invstd = -1; };
struct PfnBackwardArgs {
  int points = -1, w = -1, argmax = -1, dout = -1, dw = -1, dgamma = -1, dbeta = -1, save_mean = -1,
      save_invstd = -1;
};
struct ScatterArgs { int features = -1, cells = -1, canvas = -1; };
struct ScatterBackwardArgs { int dcanvas = -1, cells = -1, dfeatures = -1; };
struct CopyChannelsArgs { int x = -1, y = -1; };
struct ExtractChannelsArgs { int y = -1, x = -1; };
struct Conv2dArgs { int x = -1, w = -1, bias = -1, y = -1; };
struct Conv2dBackwardArgs { int x = -1, w = -1, dy = -1, dx = -1, dw = -1, dbias = -1; };
struct BatchNormReluArgs { int x = -1, y = -1, save_mean = -1, save_invstd = -1; };
struct BatchNormReluBackwardArgs {
  int x = -1, y = -1, dy = -1, save_mean = -1, save_invstd = -1, dx = -1, dgamma = -1, dbeta = -1;
};
struct MaxPool2dArgs { int x = -1, y = -1, argmax = -1; };
struct MaxPool2dBackwardArgs { int dy = -1, argmax = -1, dx = -1; };
struct UnaryArgs { int x = -1, y = -1; };  // UpsampleBilinear, its backward (dy, dx), Convert
struct PadConcatArgs { int skip = -1, up = -1, y = -1; };
struct PadConcatBackwardArgs { int dy = -1, dskip = -1, dup = -1; };
struct AddInplaceArgs { int a = -1, b = -1; };
struct LossArgs { int logits = -1, labels = -1, coefficients = -1, dlogits = -1; };
// prepared_scale: INT8 weights' per-output-channel scales (absent for 16-bit weights).
struct PrepareConvWeightsArgs {
  int w = -1, bias = -1, prepared = -1, prepared_bias = -1, transformed = -1, prepared_scale = -1;
};
struct PreparedConv2dArgs {
  int x = -1, prepared = -1, prepared_bias = -1, transformed = -1, y = -1, prepared_scale = -1;
};

enum class Access { Read, Write, ReadWrite };

// The dtypes an argument takes, as a set.
using DTypes = uint32_t;
constexpr DTypes dtypes_of(DType t) { return DTypes{1} << static_cast<unsigned>(t); }
constexpr DTypes kF32 = dtypes_of(DType::F32), kI32 = dtypes_of(DType::I32), kU8 = dtypes_of(DType::U8);
constexpr DTypes kFloat16 = dtypes_of(DType::BF16) | dtypes_of(DType::F16);
// Prepared convolution weights: 16-bit, INT8, or FP32 where a backend's FP32 kernel is the
// faster (Backend::prepared_conv_dtype).
constexpr DTypes kPrepared = kF32 | kFloat16 | dtypes_of(DType::I8);
constexpr DTypes kActivation = kF32 | kFloat16;

struct ArgSpec {
  const char* name;
  Access access;
  DTypes dtypes;
  bool optional = false;
};

// The executor's view of the running model: the memory of a node's tensors and what the model
// keeps outside the graph (BatchNorm parameters, the live pillar rows, the loss kind).
class OpContext {
 public:
  virtual ~OpContext() = default;
  virtual Backend& backend() = 0;
  virtual const Graph& graph() const = 0;
  // Tensor `id`'s memory and its shape (dim 0 of a dynamic-row tensor: the run's pillar rows).
  virtual void* data(int id) = 0;
  virtual Shape shape(int id) const = 0;
  // The BatchNorm of node n with the given save-statistics tensors (-1: none).
  virtual BatchNormRefs batchnorm(const GraphNode& n, int save_mean, int save_invstd) = 0;
  // A training-mode BatchNorm of node n ran: counts its batch (num_batches_tracked).
  virtual void batchnorm_ran(const GraphNode& n) = 0;
  virtual int64_t pillar_rows() const = 0;
  virtual IRef live_rows() const = 0;
  virtual LossSpec loss_spec() const = 0;

  template <class T>
  RefT<T> ref(int id) {
    return id < 0 ? RefT<T>{} : RefT<T>{static_cast<T*>(data(id)), shape(id)};
  }
  Ref f32(int id) { return ref<float>(id); }
  IRef i32(int id) { return ref<int32_t>(id); }
  // The tensor with its dtype (empty for -1).
  TensorRef tensor(int id);
  size_t bytes(int id);
};

struct OpRecord {
  OpKind kind;
  const char* name;  // "conv2d": the op tables of pillarseg bench
  std::vector<ArgSpec> args;
  // Checks the shapes (and dtypes beyond the per-argument sets) of a node's arguments against
  // the op's shape rule in core/ops.hpp; throws pillarseg::Error naming the node.
  void (*check)(const Graph& g, const GraphNode& n) = nullptr;
  // Multiply-adds x 2 of its arithmetic on weights (nullptr: none).
  double (*flops)(const Graph& g, const GraphNode& n) = nullptr;
  // The bytes it must move at the least, dim 0 of dynamic-row tensors being `pillar_rows`
  // (nullptr: every distinct tensor it reads and writes once, one it updates in place twice).
  size_t (*least_bytes)(const Graph& g, const GraphNode& n, int64_t pillar_rows) = nullptr;
  // Runs node n on the context's backend; the loss returns its value, the others 0.
  double (*run)(OpContext& ctx, const GraphNode& n) = nullptr;
  // Its arithmetic runs on matrix units (tensor cores, AMX) when its compute dtype is 16-bit.
  bool matrix_op = false;
};

const OpRecord& op_record(OpKind kind);
const char* op_name(OpKind kind);
// The record's name; with the node's dtype where it is not FP32 ("maxpool forward bf16"), and on
// a CUDA device " (tensor cores)" where on_matrix_units (the CPU's matrix instructions, VNNI, AMX
// or AVX512_BF16, depend on the CPU: `bench` names them in its header): the key of the per-op
// timing.
std::string op_label(const Graph& g, const GraphNode& n, Device device);
// Whether node n's arithmetic runs on matrix units (tensor cores, AMX; the roofline's 16-bit or
// INT8 peak): a matrix op whose compute dtype is 16-bit or INT8.
bool on_matrix_units(const Graph& g, const GraphNode& n);
// ... and whether at the INT8 rate (a matrix op on INT8 prepared weights).
bool on_int8_units(const Graph& g, const GraphNode& n);

// A node's arguments as the op's struct, and back.
template <class Args>
std::vector<int> args_vector(const Args& a) {
  static_assert(sizeof(Args) % sizeof(int) == 0);
  const auto* p = reinterpret_cast<const int*>(&a);
  return std::vector<int>(p, p + sizeof(Args) / sizeof(int));
}

}  // namespace pillarseg
