// Every op of the Backend interface on every backend of this build against the reference, from
// one table of cases, in the manner of ggml's test-backend-ops:
//   - the backends under test: the CPU backend (its Winograd, fused, BF16 and INT8 paths; BF16 and
//     INT8 on the models of the AVX512_BF16 and AVX512-VNNI instructions where this CPU lacks
//     them), and the CUDA backend, on the emulation in test_backend_ops and on the GPU in
//     test_backend_ops_gpu;
//   - the reference: the CPU reference backend (host/ ops alone), or, for the 16-bit and INT8 ops,
//     which it does not have, the op's definition written here on host memory from host/ ops, the
//     rounding of weights_io/half.hpp and the INT8 rules of engine/cpu/int8_conv.hpp;
//   - each case names the op, its dtype and its shapes ("conv2d_prepared_forward/bf16,x=...,w=..."),
//     and gives its tensors (inputs, outputs, and in-outs such as a canvas that an op writes a
//     band of, or running statistics) with their random contents;
//   - every tensor lies between guard words: an op that writes a byte outside its tensor fails,
//     and outputs start as NaN (integers as junk) so that an element left unwritten fails too;
//   - results are compared bit for bit where the op is exact (data movement, integer outputs,
//     one rounding of one value), else per element by |a - r| <= atol + rtol |r| or, for large
//     reductions, by normalised mean squared error sum (a - r)^2 / sum r^2; NaN and Inf must
//     match, and a failure names the worst element.
//
// The ops of backend.hpp and the cases that cover them, FP32 unless a dtype is named; "empty,"
// marks a batch of 0 (memory, clock, capture and counters are the harness's own calls, not ops):
//   pad_points                  pad_points/m=..,num=..       (0 and 1 point, none padded, all)
//   pillar_gather               pillar_gather/m=..,n=..,max=..  (0 and 1 point, capped, uncapped)
//   decorate_points             decorate_points/...          (live rows, and every row live)
//   batch_cells                 batch_cells/rows=..,sample=..   (0 and 1 row, inert rows)
//   observability_2d            observability_2d/...         (origin on a corner, outside)
//   observability_input         observability_input/...
//   occupancy_3d                occupancy_3d/...
//   grid_map_features           grid_map_features/...
//   mask_unobserved             mask_unobserved/...          (with and without probabilities)
//   pfn_forward                 pfn_forward/eval|train|live=..   (1 pillar of 1 point, of 3)
//   pfn_backward                pfn_backward/[twin_replicas,]... (synchronised BatchNorm)
//   scatter_forward             scatter_forward/...          (0 and 1 pillar)
//   scatter_backward            scatter_backward/...
//   copy_channels               copy_channels/...
//   extract_channels            extract_channels/...
//   conv2d_forward              conv2d_forward/[no_bias,|empty,]...
//   conv2d_backward             conv2d_backward/[dw_only,]...
//   conv_transpose2d_forward    conv_transpose2d_forward/[no_bias,]...
//   conv_transpose2d_backward   conv_transpose2d_backward/[no_bias,]...
//   conv2d_bn_relu_eval         conv2d_bn_relu_eval/[no_bias,]...
//   batchnorm_relu_forward      batchnorm_relu_forward/eval[,empty]|train|train,twin_replicas
//   batchnorm_relu_backward     batchnorm_relu_backward/[twin_replicas,|in_place,]...
//   maxpool2d_forward          maxpool2d_forward/[empty,]...  (a 1 x 1 output; NaN, -Inf, ties)
//   maxpool2d_backward         maxpool2d_backward/...
//   upsample_bilinear_forward          upsample_bilinear_forward/[empty,]...  (a 1 x 1 input)
//   upsample_bilinear_backward         upsample_bilinear_backward/...
//   pad_concat_forward          pad_concat_forward/[empty,]...  (1 x 1 planes)
//   pad_concat_backward         pad_concat_backward/...
//   add_inplace                 add_inplace/...              (0 and 1 element)
//   softmax                     softmax/[large,|empty,]...  (one cell)
//   argmax                      argmax/[ties,|empty,]...
//   mirror_add                  mirror_add/[y,][x,]...       (each mirror; a 1 x 1 map)
//   argmax_positive             argmax_positive/...          (no positive value, ties, NaN)
//   loss                        loss/ce|bce|ce+lovasz[,large|,unlabelled|,empty]  (logits up
//                                                            to +-100, no labelled cell, a batch
//                                                            of 0; the Lovász term weighted 0.5)
//   sum_of_squares              sum_of_squares/n=..          (0 and 1 element)
//   scale                       scale/n=..                   (0 and 1 element)
//   adam_step                   adam_step/n=..               (1 element; AdamW, Adam)
//   begin_sum_over_replicas,    sum_over_replicas/n=..       (two pieces, two replicas: the
//   end_sums_over_replicas                                   CPU's and the emulation's host
//                                                            path; a GPU's NCCL path needs
//                                                            processes: tests/mpi)
//   supports_precision, supports_training_precision, supports_synchronized_batchnorm: the cases
//                               that need them ask the backend first (and record why not)
//   prepared_conv_transform_elements  conv2d_prepared_forward/... (the CPU's Winograd U)
//   prepare_conv_weights        prepare_conv_weights/bf16|fp16|int8  (bias, BatchNorm folded,
//                                                            neither; int8 with weight_scale, an
//                                                            all-zero output channel)
//   prepare_conv_transpose_weights  prepare_conv_transpose_weights/bf16|fp16|int8
//   conv2d_prepared_forward     conv2d_prepared_forward/bf16|fp16|int8  (x and y FP32 or 16-bit;
//                                                            int8: x and y FP32 or BF16, the
//                                                            Int8Input signed and non_negative,
//                                                            clamped values, NaN, +-Inf, ties,
//                                                            K padded)
//   conv_transpose2d_prepared_forward  conv_transpose2d_prepared_forward/bf16|fp16|int8
//                                                            (int8: signed and non_negative)
//   conv2d_backward (compute 16-bit)  conv2d_backward/bf16|fp16[,dw_only]
//   conv_transpose2d_backward (compute 16-bit)  conv_transpose2d_backward/bf16|fp16
//   convert                     convert/bf16|fp16            (ties, overflow, subnormals, NaN)
//   maxpool2d_forward (16-bit)  maxpool2d_forward/bf16|fp16    (NaN, -Inf, ties)
//   upsample_bilinear_forward (16-bit)  upsample_bilinear_forward/bf16|fp16
//   pad_concat_forward (16-bit)  pad_concat_forward/bf16|fp16
//   copy_channels (16-bit)      copy_channels/bf16|fp16
//   scatter_forward (16-bit canvas)  scatter_forward/bf16|fp16  (0 and 1 pillar, inert rows)
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <memory>
#include <numeric>
#include <optional>
#include <sstream>
#include <string>
#include <string_view>
#include <vector>

#include "core/ops.hpp"
#include "core/replicas.hpp"
#include "core/rng.hpp"
#include "engine/backend/backend.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "host/conv2d.hpp"
#include "host/conv_transpose2d.hpp"
#include "host/maxpool2d.hpp"
#include "host/pad_concat.hpp"
#include "host/upsample_bilinear.hpp"
#include "tests/support/scans.hpp"
#include "weights_io/half.hpp"

using namespace pillarseg;

namespace {

// H16: BF16 or FP16 bits, as the case's precision (BF16 in an INT8 case); I8: int8 values.
enum class Kind { F32, I32, U32, U8, H16, I8 };
enum class Role { Input, Output, InOut };

constexpr size_t kGuardBytes = 64;
constexpr uint8_t kGuardByte = 0xA5;

size_t kind_bytes(Kind k) {
  return k == Kind::U8 || k == Kind::I8 ? 1 : k == Kind::H16 ? 2 : 4;
}

std::string shape_name(const Shape& s) {
  std::string out;
  for (size_t i = 0; i < s.size(); ++i) {
    if (i > 0) out.push_back('x');
    out.append(std::to_string(s[i]));
  }
  return out;
}

// The 16-bit type of a case of precision p: p's, or BF16 for INT8 (its activations' 16-bit type).
Precision half_type(Precision p) {
  return p == Precision::I8 ? Precision::BF16 : p;
}
uint16_t to_bits(float v, Precision p) {
  return half_type(p) == Precision::BF16 ? weights::float_to_bf16_bits(v)
                                         : weights::float_to_f16_bits(v);
}
float from_bits(uint16_t h, Precision p) {
  return half_type(p) == Precision::BF16 ? weights::bf16_bits_to_float(h)
                                         : weights::f16_bits_to_float(h);
}
// v rounded to the 16-bit type of p.
float rounded(float v, Precision p) {
  return from_bits(to_bits(v, p), p);
}
// One unit in the last place of a 16-bit value, relative: the most one rounding of the output
// may move it.
double half_ulp(Precision p) {
  return p == Precision::BF16 ? 0x1p-7 : 0x1p-10;
}

// How an output compares with the reference's.
struct Tolerance {
  enum class Mode { Bits, Nmse, Elementwise } mode = Mode::Nmse;
  double max_nmse = 1e-10, atol = 0, rtol = 0;
};
Tolerance bits() {
  return {Tolerance::Mode::Bits};
}
Tolerance nmse_within(double max_nmse) {
  return {Tolerance::Mode::Nmse, max_nmse};
}
Tolerance within(double atol, double rtol) {
  return {Tolerance::Mode::Elementwise, 0, atol, rtol};
}

struct Arg {
  std::string name;
  Shape shape;
  Kind kind = Kind::F32;
  Role role = Role::Input;
  // Fills the host bytes of an input or in-out (numel elements of `kind`).
  std::function<void(Rng&, void*, int64_t)> fill;
  std::optional<Tolerance> tol = std::nullopt;  // instead of the case's
  // An output of the pillar gather's leading rows: the arg whose first int32 counts them (as the
  // reference wrote it); the rows past it are compared only where a backend said it wrote them
  // (Bound::rows), with `inert`.
  int live_rows_from = -1;
  std::optional<double> inert = std::nullopt;
  size_t bytes() const { return static_cast<size_t>(shape_numel(shape)) * kind_bytes(kind); }
};

// The case's tensors in one backend's memory, each between two guard regions.
class Bound {
 public:
  Bound(Backend& be, const std::vector<Arg>& args, const std::vector<std::vector<uint8_t>>& host)
      : be_(be), args_(&args) {
    for (size_t i = 0; i < args.size(); ++i) {
      const size_t total = args[i].bytes() + 2 * kGuardBytes;
      std::vector<uint8_t> image(total, kGuardByte);
      std::copy(host[i].begin(), host[i].end(), image.begin() + kGuardBytes);
      uint8_t* block = static_cast<uint8_t*>(be.allocate(total));
      be.upload(block, image.data(), total);
      blocks_.push_back(block);
      sizes_.push_back(total);
    }
  }
  ~Bound() {
    for (uint8_t* b : blocks_) be_.deallocate(b);
  }
  Bound(const Bound&) = delete;
  Bound& operator=(const Bound&) = delete;

  template <class T>
  RefT<T> ref(size_t i) {
    return {reinterpret_cast<T*>(blocks_[i] + kGuardBytes), (*args_)[i].shape};
  }
  Ref f(size_t i) { return ref<float>(i); }
  IRef i32(size_t i) { return ref<int32_t>(i); }
  URef u32(size_t i) { return ref<uint32_t>(i); }
  LRef u8(size_t i) { return ref<uint8_t>(i); }
  HRef h16(size_t i) { return ref<uint16_t>(i); }
  RefT<int8_t> i8(size_t i) { return ref<int8_t>(i); }
  // A tensor with its dtype: 16-bit in precision p's 16-bit type where the arg's kind is, int8
  // where it is I8, else FP32.
  TensorRef tensor(size_t i, Precision p) {
    const Kind kind = (*args_)[i].kind;
    return {blocks_[i] + kGuardBytes, (*args_)[i].shape,
            kind == Kind::H16 ? dtype_of(half_type(p)) : kind == Kind::I8 ? DType::I8 : DType::F32};
  }
  // The same for the references' helpers below.
  ActRef act(size_t i) {
    return {blocks_[i] + kGuardBytes, (*args_)[i].shape, (*args_)[i].kind == Kind::H16};
  }
  BatchNormRefs bn(size_t first, bool with_saved) {
    BatchNormRefs r;
    r.gamma = f(first), r.beta = f(first + 1), r.running_mean = f(first + 2),
    r.running_var = f(first + 3);
    if (with_saved) r.save_mean = f(first + 4), r.save_invstd = f(first + 5);
    return r;
  }
  // The tensor's bytes and whether both guard regions are intact.
  std::vector<uint8_t> download(size_t i, bool& guards_intact) {
    std::vector<uint8_t> image(sizes_[i]);
    be_.synchronize();
    be_.download(image.data(), blocks_[i], sizes_[i]);
    guards_intact = true;
    for (size_t k = 0; k < kGuardBytes; ++k)
      guards_intact =
          guards_intact && image[k] == kGuardByte && image[sizes_[i] - 1 - k] == kGuardByte;
    return {image.begin() + static_cast<std::ptrdiff_t>(kGuardBytes),
            image.end() - static_cast<std::ptrdiff_t>(kGuardBytes)};
  }
  double scalar = 0;  // an op's returned value (the loss, a sum)
  int64_t rows = -1;  // the leading rows an op said it wrote (pillar_gather)

 private:
  Backend& be_;
  const std::vector<Arg>* args_;
  std::vector<uint8_t*> blocks_;
  std::vector<size_t> sizes_;
};

// Scratch a case's run takes from the backend itself (the CPU's Winograd weights, whose size
// only the backend knows); null for 0 elements.
class BackendScratch {
 public:
  BackendScratch(Backend& be, int64_t halves) : be_(be) {
    if (halves > 0) data_ = static_cast<uint16_t*>(be.allocate(static_cast<size_t>(halves) * 2));
    ref_ = {data_, {halves}};
  }
  ~BackendScratch() {
    if (data_ != nullptr) be_.deallocate(data_);
  }
  BackendScratch(const BackendScratch&) = delete;
  BackendScratch& operator=(const BackendScratch&) = delete;
  const HRef& ref() const { return ref_; }
  TensorRef tensor(Precision p) const { return {ref_.data, ref_.shape, dtype_of(p)}; }

 private:
  Backend& be_;
  uint16_t* data_ = nullptr;
  HRef ref_;
};

struct Case {
  std::string name;
  std::vector<Arg> args;
  std::function<void(Backend&, Bound&)> run;
  Tolerance tol = nmse_within(1e-12);
  bool compare_scalar = false;
  // The 16-bit type of the H16 args and of the op (F32: the op has none); a backend runs the case
  // where supports_precision (supports_training_precision for `training`) says it can.
  Precision precision = Precision::F32;
  bool training = false;
  // The op's definition on host memory (the reference backend's), for the ops the reference
  // backend lacks; else the reference backend runs `run`.
  std::function<void(Bound&)> reference = nullptr;
  // The CPU backend's own bound where its algorithm rounds differently (the BF16 Winograd).
  std::optional<Tolerance> cpu_tol = std::nullopt;
  // Whether a backend runs the case at all, else why not (besides the precision).
  std::function<bool(const Backend&, std::string&)> runs_on = nullptr;
};

// ---- argument makers ----

Arg in_f(std::string name, Shape shape, double lo = -1, double hi = 1) {
  Arg a{std::move(name), std::move(shape), Kind::F32, Role::Input, {}};
  a.fill = [lo, hi](Rng& rng, void* p, int64_t n) {
    float* f = static_cast<float*>(p);
    for (int64_t i = 0; i < n; ++i) f[i] = static_cast<float>(rng.uniform(lo, hi));
  };
  return a;
}
Arg inout_f(std::string name, Shape shape, double lo = -1, double hi = 1) {
  Arg a = in_f(std::move(name), std::move(shape), lo, hi);
  a.role = Role::InOut;
  return a;
}
// 16-bit values of type p, uniform in [lo, hi) before rounding.
Arg in_h(std::string name, Shape shape, Precision p, double lo = -1, double hi = 1) {
  Arg a{std::move(name), std::move(shape), Kind::H16, Role::Input, {}};
  a.fill = [p, lo, hi](Rng& rng, void* dst, int64_t n) {
    uint16_t* h = static_cast<uint16_t*>(dst);
    for (int64_t i = 0; i < n; ++i) h[i] = to_bits(static_cast<float>(rng.uniform(lo, hi)), p);
  };
  return a;
}
// The max-pool's hard inputs among the random values: NaN (which wins), -Inf, and ties (which
// keep the window's first element), at fixed positions.
Arg with_nan_and_ties(Arg a, Precision p = Precision::F32) {
  a.fill = [fill = a.fill, kind = a.kind, p](Rng& rng, void* dst, int64_t n) {
    fill(rng, dst, n);
    for (int64_t i = 0; i < n; ++i) {
      float special;
      if (i % 7 == 3)
        special = std::numeric_limits<float>::quiet_NaN();
      else if (i % 11 == 5)
        special = -std::numeric_limits<float>::infinity();
      else if (i % 3 == 1)
        special = 0.5f;
      else
        continue;
      if (kind == Kind::H16)
        static_cast<uint16_t*>(dst)[i] = to_bits(special, p);
      else
        static_cast<float*>(dst)[i] = special;
    }
  };
  return a;
}
Arg inout_h(std::string name, Shape shape, Precision p) {
  Arg a = in_h(std::move(name), std::move(shape), p);
  a.role = Role::InOut;
  return a;
}
Arg in_i32(std::string name, Shape shape, std::function<int32_t(Rng&, int64_t)> value) {
  Arg a{std::move(name), std::move(shape), Kind::I32, Role::Input, {}};
  a.fill = [value](Rng& rng, void* dst, int64_t n) {
    int32_t* v = static_cast<int32_t*>(dst);
    for (int64_t i = 0; i < n; ++i) v[i] = value(rng, i);
  };
  return a;
}
Arg out(std::string name, Shape shape, Kind kind = Kind::F32) {
  return {std::move(name), std::move(shape), kind, Role::Output, {}};
}
// BatchNorm parameters and running statistics (C) each, then, with `saved`, the two (C) outputs
// of a training forward (or its inputs to a backward, `saved_in`).
void add_bn(std::vector<Arg>& args, int64_t c, bool running_out, bool saved_out,
            bool saved_in = false) {
  args.push_back(in_f("gamma", {c}, 0.5, 1.5));
  args.push_back(in_f("beta", {c}, -0.5, 0.5));
  Arg mean = in_f("running_mean", {c}, -0.2, 0.2), var = in_f("running_var", {c}, 0.5, 2);
  if (running_out) mean.role = var.role = Role::InOut;
  args.push_back(mean);
  args.push_back(var);
  if (saved_out) {
    args.push_back(out("save_mean", {c}));
    args.push_back(out("save_invstd", {c}));
  } else if (saved_in) {
    args.push_back(in_f("save_mean", {c}, -0.2, 0.2));
    args.push_back(in_f("save_invstd", {c}, 0.5, 2));
  }
}
// Cells (P, 3) of P distinct (sample, iy, ix) of a (B, H, W) grid; with `inert`, every fourth
// row is an inert row's (-1, -1, -1) (the pipeline's rows past P').
Arg cells_arg(int64_t p, int64_t b, int64_t h, int64_t w, bool inert = false) {
  Arg a{"cells", {p, 3}, Kind::I32, Role::Input, {}};
  a.fill = [b, h, w, inert](Rng& rng, void* dst, int64_t n) {
    std::vector<int64_t> all(static_cast<size_t>(b * h * w));
    std::iota(all.begin(), all.end(), 0);
    rng.shuffle(all.begin(), all.end());
    int32_t* c = static_cast<int32_t*>(dst);
    for (int64_t r = 0; r < n / 3; ++r) {
      const int64_t k = all[static_cast<size_t>(r)];
      const bool dead = inert && r % 4 == 3;
      c[3 * r] = dead ? -1 : static_cast<int32_t>(k / (h * w));
      c[3 * r + 1] = dead ? -1 : static_cast<int32_t>(k / w % h);
      c[3 * r + 2] = dead ? -1 : static_cast<int32_t>(k % w);
    }
  };
  return a;
}
Arg labels_arg(Shape shape, Role role = Role::Input) {
  Arg a{"labels", std::move(shape), Kind::U8, role, {}};
  a.fill = [](Rng& rng, void* dst, int64_t n) {
    uint8_t* l = static_cast<uint8_t*>(dst);
    for (int64_t i = 0; i < n; ++i)
      l[i] = static_cast<uint8_t>(rng.uniform_int(13));  // 0 = unlabelled
  };
  return a;
}
// Ray counts (H, W): a third of the cells 0 (no ray), the others up to `largest`.
Arg counts_arg(std::string name, Shape shape, uint32_t largest) {
  Arg a{std::move(name), std::move(shape), Kind::U32, Role::Input, {}};
  a.fill = [largest](Rng& rng, void* dst, int64_t n) {
    uint32_t* c = static_cast<uint32_t*>(dst);
    for (int64_t i = 0; i < n; ++i)
      c[i] = rng.uniform_int(3) == 0 ? 0u : static_cast<uint32_t>(1 + rng.uniform_int(largest));
  };
  return a;
}

// ---- the input pipeline's grid and scans ----

// A small grid with odd sides: 15 x 11 cells of 0.4 m, 5 layers of 0.4 m; the sensor origin
// (0, 0, 0) lies on a cell corner.
GridSpec small_grid() {
  GridSpec g;
  g.x_min = -2.8, g.x_max = 3.2, g.y_min = -2.0, g.y_max = 2.4, g.z_min = -1.0, g.z_max = 1.0;
  g.cell = 0.4, g.voxel_z = 0.4;
  return g;
}
// points (M, 4): crowded cells, cell borders, points outside the grid, non-finite ones.
Arg points_arg(int64_t m, const GridSpec& grid, Role role = Role::Input) {
  Arg a{"points", {m, 4}, Kind::F32, role, {}};
  a.fill = [grid](Rng& rng, void* dst, int64_t n) {
    const std::vector<Point> scan = test::random_scan(n / 4, grid, rng.uniform_int(1u << 30));
    if (!scan.empty()) std::memcpy(dst, scan.data(), scan.size() * sizeof(Point));
  };
  return a;
}
std::string origin_name(const Eigen::Vector3d& o) {
  std::ostringstream s;
  s << "origin=" << o.x() << "_" << o.y() << "_" << o.z();
  return s.str();
}

// ---- the 16-bit ops' definitions on host memory ----

// The prepared weights of a convolution (kernels/conv2d_mma.cuh's contract, its FP32
// arithmetic): w16 (O, taps Ip) with w16[o][t Ip + c] = w[o][c][t] s rounded (0 for c >= I),
// bias_out[o] = s bias[o] + beta - s mean, s = gamma / sqrt(var + eps) (1 without BatchNorm).
void define_prepare_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn,
                                 Precision p, HRef& w16, Ref& bias_out) {
  const int64_t out_channels = w.dim(0), in = w.dim(1), taps = w.dim(2) * w.dim(3);
  const int64_t padded = op::half16_padded_channels(in), kp = w16.dim(1);
  for (int64_t o = 0; o < out_channels; ++o) {
    float s = 1.0f, shift = 0.0f;
    if (bn != nullptr) {
      s = bn->gamma.data[o] / std::sqrt(bn->running_var.data[o] + bn->eps);
      shift = bn->beta.data[o] - s * bn->running_mean.data[o];
    }
    for (int64_t t = 0; t < taps; ++t)
      for (int64_t c = 0; c < padded; ++c)
        w16.data[o * kp + t * padded + c] =
            to_bits(c < in ? w.data[(o * in + c) * taps + t] * s : 0.0f, p);
    bias_out.data[o] = s * (bias != nullptr ? bias->data[o] : 0.0f) + shift;
  }
}
// A transposed one's: w (I, O, 2, 2) -> w16 (4 O, Ip), row 4 o + 2 dy + dx, bias_out (4 O).
void define_prepare_conv_transpose_weights(const Ref& w, const Ref* bias, Precision p, HRef& w16,
                                           Ref& bias_out) {
  const int64_t in = w.dim(0), out_channels = w.dim(1), kp = w16.dim(1);
  for (int64_t n = 0; n < 4 * out_channels; ++n) {
    const int64_t o = n / 4, s = n % 4;
    for (int64_t c = 0; c < kp; ++c)
      w16.data[n * kp + c] = to_bits(c < in ? w.data[(c * out_channels + o) * 4 + s] : 0.0f, p);
    bias_out.data[n] = bias != nullptr ? bias->data[o] : 0.0f;
  }
}
// x (FP32 or 16-bit) as the 16-bit values the convolutions multiply.
std::vector<double> rounded_activation(const ActRef& x, Precision p) {
  std::vector<double> v(static_cast<size_t>(x.numel()));
  for (size_t i = 0; i < v.size(); ++i)
    v[i] = x.half ? from_bits(static_cast<const uint16_t*>(x.data)[i], p)
                  : rounded(static_cast<const float*>(x.data)[i], p);
  return v;
}
// y[i] = value, FP32 or rounded to p.
void store(const ActRef& y, int64_t i, double value, Precision p) {
  const float v = static_cast<float>(value);
  if (y.half)
    static_cast<uint16_t*>(y.data)[i] = to_bits(v, p);
  else
    static_cast<float*>(y.data)[i] = v;
}
// y = act(conv(x, w16) + bias_out), in double on the 16-bit operands.
void define_conv2d_half_forward(const ActRef& x, const HRef& w16, const Ref& bias_out,
                                const Shape& weight, int pad, bool relu, Precision p,
                                const ActRef& y) {
  const std::vector<double> xv = rounded_activation(x, p);
  const int64_t B = x.dim(0), I = x.dim(1), H = x.dim(2), W = x.dim(3), O = weight[0],
                k = weight[2];
  const int64_t Ho = y.dim(2), Wo = y.dim(3), kp = w16.dim(1),
                padded = op::half16_padded_channels(I);
  for (int64_t b = 0; b < B; ++b)
    for (int64_t o = 0; o < O; ++o)
      for (int64_t oy = 0; oy < Ho; ++oy)
        for (int64_t ox = 0; ox < Wo; ++ox) {
          double sum = bias_out.data[o];
          for (int64_t c = 0; c < I; ++c)
            for (int64_t ky = 0; ky < k; ++ky)
              for (int64_t kx = 0; kx < k; ++kx) {
                const int64_t iy = oy + ky - pad, ix = ox + kx - pad;
                if (iy < 0 || iy >= H || ix < 0 || ix >= W) continue;
                sum += xv[static_cast<size_t>(((b * I + c) * H + iy) * W + ix)] *
                       from_bits(w16.data[o * kp + (ky * k + kx) * padded + c], p);
              }
          store(y, ((b * O + o) * Ho + oy) * Wo + ox, relu ? std::max(sum, 0.0) : sum, p);
        }
}
// y (B, O, 2H, 2W): y[b][o][2i + dy][2j + dx] = bias_out[4 o + 2 dy + dx] + sum_c x[b][c][i][j]
// w16[4 o + 2 dy + dx][c], in double on the 16-bit operands.
void define_conv_transpose2d_half_forward(const ActRef& x, const HRef& w16, const Ref& bias_out,
                                           const Shape& weight, Precision p, const ActRef& y) {
  const std::vector<double> xv = rounded_activation(x, p);
  const int64_t B = x.dim(0), I = x.dim(1), H = x.dim(2), W = x.dim(3), O = weight[1],
                kp = w16.dim(1);
  for (int64_t b = 0; b < B; ++b)
    for (int64_t n = 0; n < 4 * O; ++n)
      for (int64_t i = 0; i < H; ++i)
        for (int64_t j = 0; j < W; ++j) {
          double sum = bias_out.data[n];
          for (int64_t c = 0; c < I; ++c)
            sum += xv[static_cast<size_t>(((b * I + c) * H + i) * W + j)] *
                   from_bits(w16.data[n * kp + c], p);
          const int64_t o = n / 4, dy = n % 4 / 2, dx = n % 2;
          store(y, ((b * O + o) * 2 * H + 2 * i + dy) * 2 * W + 2 * j + dx, sum, p);
        }
}
// dbias (O) of dy (B, O, h, w): summed in double from the FP32 dy (not rounded, as the 16-bit
// backward's contract says).
void define_bias_gradient(const Ref& dy, Ref& dbias) {
  const int64_t B = dy.dim(0), O = dy.dim(1), plane = dy.dim(2) * dy.dim(3);
  for (int64_t o = 0; o < O; ++o) {
    double sum = 0;
    for (int64_t b = 0; b < B; ++b)
      for (int64_t i = 0; i < plane; ++i) sum += dy.data[(b * O + o) * plane + i];
    dbias.data[o] = static_cast<float>(sum);
  }
}
// A copy of an FP32 tensor with every value rounded to p (the operands of the 16-bit backward).
Tensor<float> rounded_copy(const Ref& r, Precision p) {
  Tensor<float> t(r.shape);
  for (int64_t i = 0; i < r.numel(); ++i) t.data()[i] = rounded(r.data[i], p);
  return t;
}
Tensor<float> decoded(const HRef& h, Precision p) {
  Tensor<float> t(h.shape);
  for (int64_t i = 0; i < h.numel(); ++i) t.data()[i] = from_bits(h.data[i], p);
  return t;
}
void encode(const Tensor<float>& t, Precision p, HRef& h) {
  for (int64_t i = 0; i < h.numel(); ++i) h.data[i] = to_bits(t.data()[i], p);
}

// ---- the INT8 ops' definitions on host memory (engine/cpu/int8_conv.hpp's contract, which
// kernels/conv2d_mma_s8.cuh shares) ----

// An INT8 weight: clamp(round_half_even(v / sw), -127, 127), 0 where sw is 0 (an all-zero channel).
int8_t quantize_weight(float v, float sw) {
  if (sw == 0.0f) return 0;
  return static_cast<int8_t>(std::clamp(std::nearbyint(v / sw), -127.0f, 127.0f));
}
// An input value by Int8Input's rule, r = 1 / scale rounded to FP32: clamp(round_half_even(x r),
// -127, 127), or clamp(..., 0, 255) for a non-negative input; NaN 0, infinities clamped.
int32_t quantize_input(float x, float r, bool non_negative) {
  const float v = x * r;
  if (std::isnan(v)) return 0;
  return static_cast<int32_t>(std::nearbyint(
      std::clamp(v, non_negative ? 0.0f : -127.0f, non_negative ? 255.0f : 127.0f)));
}
// x (B, C, H, W), FP32 or BF16, quantized by `input`.
std::vector<int32_t> quantized_input(const ActRef& x, Int8Input input) {
  const float r = 1.0f / input.scale;
  std::vector<int32_t> q(static_cast<size_t>(x.numel()));
  for (size_t i = 0; i < q.size(); ++i) {
    const float v = x.half ? weights::bf16_bits_to_float(static_cast<const uint16_t*>(x.data)[i])
                           : static_cast<const float*>(x.data)[i];
    q[i] = quantize_input(v, r, input.non_negative);
  }
  return q;
}
// y[i] = act(fma(float(acc), scale, bias)), FP32 or rounded to BF16; the ReLU max(v, 0).
void store_int8_result(const ActRef& y, int64_t i, int32_t acc, float scale, float bias,
                       bool relu) {
  float v = std::fma(static_cast<float>(acc), scale, bias);
  if (relu) v = v > 0.0f ? v : 0.0f;
  if (y.half)
    static_cast<uint16_t*>(y.data)[i] = weights::float_to_bf16_bits(v);
  else
    static_cast<float*>(y.data)[i] = v;
}
// A convolution's INT8 weights: w' = w s with the BatchNorm folded in as in
// define_prepare_conv_weights (bias_out too), weight_scale[o] = max |w'[o]| / 127, q8 (O, Kp)
// tap-major as the 16-bit weights (q8[o][t Ip + c], 0 for c >= I).
void define_prepare_int8_conv_weights(const Ref& w, const Ref* bias, const BatchNormRefs* bn,
                                      RefT<int8_t>& q8, Ref& weight_scale, Ref& bias_out) {
  const int64_t out_channels = w.dim(0), in = w.dim(1), taps = w.dim(2) * w.dim(3);
  const int64_t padded = op::half16_padded_channels(in), kp = q8.dim(1);
  for (int64_t o = 0; o < out_channels; ++o) {
    float s = 1.0f, shift = 0.0f;
    if (bn != nullptr) {
      s = bn->gamma.data[o] / std::sqrt(bn->running_var.data[o] + bn->eps);
      shift = bn->beta.data[o] - s * bn->running_mean.data[o];
    }
    const auto folded = [&](int64_t c, int64_t t) { return w.data[(o * in + c) * taps + t] * s; };
    float max_abs = 0.0f;
    for (int64_t c = 0; c < in; ++c)
      for (int64_t t = 0; t < taps; ++t) max_abs = std::max(max_abs, std::abs(folded(c, t)));
    const float sw = max_abs / 127.0f;
    weight_scale.data[o] = sw;
    for (int64_t t = 0; t < taps; ++t)
      for (int64_t c = 0; c < padded; ++c)
        q8.data[o * kp + t * padded + c] = c < in ? quantize_weight(folded(c, t), sw) : int8_t{0};
    bias_out.data[o] = s * (bias != nullptr ? bias->data[o] : 0.0f) + shift;
  }
}
// A transposed one's: w (I, O, 2, 2) -> q8 (4 O, Ip), row 4 o + 2 dy + dx; the scale of output
// channel o (max over its I x 4 weights / 127) and its bias in each of its four rows.
void define_prepare_int8_conv_transpose_weights(const Ref& w, const Ref* bias, RefT<int8_t>& q8,
                                                Ref& weight_scale, Ref& bias_out) {
  const int64_t in = w.dim(0), out_channels = w.dim(1), kp = q8.dim(1);
  for (int64_t o = 0; o < out_channels; ++o) {
    float max_abs = 0.0f;
    for (int64_t c = 0; c < in; ++c)
      for (int64_t s = 0; s < 4; ++s)
        max_abs = std::max(max_abs, std::abs(w.data[(c * out_channels + o) * 4 + s]));
    const float sw = max_abs / 127.0f;
    for (int64_t s = 0; s < 4; ++s) {
      const int64_t n = 4 * o + s;
      for (int64_t c = 0; c < kp; ++c)
        q8.data[n * kp + c] =
            c < in ? quantize_weight(w.data[(c * out_channels + o) * 4 + s], sw) : int8_t{0};
      weight_scale.data[n] = sw;
      bias_out.data[n] = bias != nullptr ? bias->data[o] : 0.0f;
    }
  }
}
// y = act(acc sx weight_scale[o] + bias_out[o]) with the exact integer sums acc of q8 and x
// quantized by `input` (the padding 0), the epilogue store_int8_result's.
void define_int8_conv2d_forward(const ActRef& x, const RefT<int8_t>& q8, const Ref& weight_scale,
                                const Ref& bias_out, const Shape& weight, int pad, bool relu,
                                Int8Input input, const ActRef& y) {
  const std::vector<int32_t> xq = quantized_input(x, input);
  const int64_t B = x.dim(0), I = x.dim(1), H = x.dim(2), W = x.dim(3), O = weight[0],
                k = weight[2];
  const int64_t Ho = y.dim(2), Wo = y.dim(3), kp = q8.dim(1),
                padded = op::half16_padded_channels(I);
  for (int64_t b = 0; b < B; ++b)
    for (int64_t o = 0; o < O; ++o)
      for (int64_t oy = 0; oy < Ho; ++oy)
        for (int64_t ox = 0; ox < Wo; ++ox) {
          int32_t acc = 0;
          for (int64_t c = 0; c < I; ++c)
            for (int64_t ky = 0; ky < k; ++ky)
              for (int64_t kx = 0; kx < k; ++kx) {
                const int64_t iy = oy + ky - pad, ix = ox + kx - pad;
                if (iy < 0 || iy >= H || ix < 0 || ix >= W) continue;
                acc += xq[static_cast<size_t>(((b * I + c) * H + iy) * W + ix)] *
                       q8.data[o * kp + (ky * k + kx) * padded + c];
              }
          store_int8_result(y, ((b * O + o) * Ho + oy) * Wo + ox, acc,
                            input.scale * weight_scale.data[o], bias_out.data[o], relu);
        }
}
// y (B, O, 2H, 2W): y[b][o][2i + dy][2j + dx] from acc = sum_c xq[b][c][i][j] q8[n][c], n = 4 o +
// 2 dy + dx, no activation.
void define_int8_conv_transpose2d_forward(const ActRef& x, const RefT<int8_t>& q8,
                                          const Ref& weight_scale, const Ref& bias_out,
                                          const Shape& weight, Int8Input input, const ActRef& y) {
  const std::vector<int32_t> xq = quantized_input(x, input);
  const int64_t B = x.dim(0), I = x.dim(1), H = x.dim(2), W = x.dim(3), O = weight[1],
                kp = q8.dim(1);
  for (int64_t b = 0; b < B; ++b)
    for (int64_t n = 0; n < 4 * O; ++n)
      for (int64_t i = 0; i < H; ++i)
        for (int64_t j = 0; j < W; ++j) {
          int32_t acc = 0;
          for (int64_t c = 0; c < I; ++c)
            acc += xq[static_cast<size_t>(((b * I + c) * H + i) * W + j)] * q8.data[n * kp + c];
          const int64_t o = n / 4, dy = n % 4 / 2, dx = n % 2;
          store_int8_result(y, ((b * O + o) * 2 * H + 2 * i + dy) * 2 * W + 2 * j + dx, acc,
                            input.scale * weight_scale.data[n], bias_out.data[n], false);
        }
}

// A data-parallel run of two replicas where the other holds the same values: every piece begun
// is doubled when the sums end (a backend hands the CPU's memory over in place, the emulated CUDA
// backend's through the host).
class TwinReplicas final : public Replicas {
 public:
  int rank() const override { return 0; }
  int size() const override { return 2; }
  void sum(double* values, int64_t n) override { twice(values, n); }
  void sum(int64_t* values, int64_t n) override { twice(values, n); }
  void begin_sum(float* values, int64_t n) override { pieces_.push_back({values, n}); }
  void progress() override {}
  void end_sums() override {
    for (const auto& [values, n] : pieces_) twice(values, n);
    pieces_.clear();
  }
  void broadcast(void*, size_t) override {}
  [[noreturn]] void abort_all(const std::string& message) override { throw Error(message); }

 private:
  template <class T>
  static void twice(T* values, int64_t n) {
    for (int64_t i = 0; i < n; ++i) values[i] *= 2;
  }
  std::vector<std::pair<float*, int64_t>> pieces_;
};

// Synchronised BatchNorm's statistics over two replicas that hold the same values: each sum
// doubles (counts included, so the means stay and the unbiased variance's n - 1 grows).
class TwinStatistics final : public ReplicaSum {
 public:
  void sum(double* values, int64_t n) override {
    for (int64_t i = 0; i < n; ++i) values[i] *= 2;
  }
};
bool synchronises_batchnorm(const Backend& be, std::string& why) {
  return be.supports_synchronized_batchnorm(&why);
}

// ---- the table ----

void add_input_ops(std::vector<Case>& all) {
  const GridSpec grid = small_grid();
  const int64_t H = grid.height(), W = grid.width(), Z = grid.layers();
  for (const auto& [m, live] :
       std::vector<std::pair<int64_t, int64_t>>{{0, 0}, {1, 0}, {1, 1}, {37, 20}, {37, 37}}) {
    all.push_back({.name = "pad_points/m=" + std::to_string(m) + ",num=" + std::to_string(live),
                   .args = {points_arg(m, grid, Role::InOut),
                            in_i32("num_points", {1},
                                   [live](Rng&, int64_t) { return static_cast<int32_t>(live); })},
                   .run =
                       [](Backend& be, Bound& t) {
                         Ref points = t.f(0);
                         be.pad_points(t.i32(1), points);
                       },
                   .tol = bits()});
  }
  // The gather's outputs past P' (num_pillars) are inert where a backend reports them written.
  const auto gather_args = [&](int64_t m, int64_t n, int max_pillars) {
    const int64_t rows = pillar_rows(m, grid, max_pillars);
    std::vector<Arg> args = {points_arg(m, grid), out("cell", {rows, 2}, Kind::I32),
                             out("point_index", {rows, n}, Kind::I32),
                             out("count", {rows}, Kind::I32), out("num_pillars", {1}, Kind::I32)};
    for (size_t i = 1; i <= 3; ++i) {
      args[i].live_rows_from = 4;
      args[i].inert = i == 3 ? 0 : -1;
    }
    return args;
  };
  for (const auto& [m, n, max_pillars] : std::vector<std::tuple<int64_t, int64_t, int>>{
           {0, 4, 0}, {0, 4, 3}, {1, 1, 0}, {300, 5, 0}, {300, 20, 7}, {300, 3, 200}}) {
    const std::string shapes = "m=" + std::to_string(m) + ",n=" + std::to_string(n) +
                               ",max=" + std::to_string(max_pillars);
    all.push_back({.name = "pillar_gather/" + shapes,
                   .args = gather_args(m, n, max_pillars),
                   .run =
                       [grid, max_pillars](Backend& be, Bound& t) {
                         IRef cell = t.i32(1), index = t.i32(2), count = t.i32(3), num = t.i32(4);
                         t.rows =
                             be.pillar_gather(t.f(0), grid, max_pillars, cell, index, count, num);
                       },
                   .tol = bits()});
    // Decoration after the gather, on the live rows (the pipeline's way: num_pillars is P').
    std::vector<Arg> args = gather_args(m, n, max_pillars);
    args.push_back(out("decorated", {pillar_rows(m, grid, max_pillars), n, 10}));
    args.back().live_rows_from = 4;
    all.push_back({.name = "decorate_points/live," + shapes,
                   .args = args,
                   .run =
                       [grid, max_pillars](Backend& be, Bound& t) {
                         IRef cell = t.i32(1), index = t.i32(2), count = t.i32(3), num = t.i32(4);
                         be.pillar_gather(t.f(0), grid, max_pillars, cell, index, count, num);
                         Ref decorated = t.f(5);
                         be.decorate_points(t.f(0), grid, cell, index, count, num, decorated);
                       },
                   .tol = bits()});
  }
  // Every row live: more pillars than P = 5 rows, so P' = R on every backend.
  {
    std::vector<Arg> args = {points_arg(300, grid),
                             out("cell", {5, 2}, Kind::I32),
                             out("point_index", {5, 6}, Kind::I32),
                             out("count", {5}, Kind::I32),
                             out("num_pillars", {1}, Kind::I32),
                             out("decorated", {5, 6, 10})};
    all.push_back({.name = "decorate_points/all,m=300,n=6,max=5",
                   .args = args,
                   .run =
                       [grid](Backend& be, Bound& t) {
                         IRef cell = t.i32(1), index = t.i32(2), count = t.i32(3), num = t.i32(4);
                         be.pillar_gather(t.f(0), grid, 5, cell, index, count, num);
                         Ref decorated = t.f(5);
                         be.decorate_points(t.f(0), grid, cell, index, count, IRef{}, decorated);
                       },
                   .tol = bits()});
  }
  for (const auto& [rows, sample] :
       std::vector<std::pair<int64_t, int>>{{0, 0}, {1, 2}, {45, 0}, {45, 3}}) {
    all.push_back(
        {.name = "batch_cells/rows=" + std::to_string(rows) + ",sample=" + std::to_string(sample),
         .args = {in_i32("cell", {rows, 2},
                         [H, W](Rng& rng, int64_t i) {
                           // Every third row inert (-1, -1), as the gather leaves rows past P'.
                           if (i / 2 % 3 == 2) return -1;
                           return static_cast<int32_t>(
                               rng.uniform_int(static_cast<uint64_t>(i % 2 == 0 ? H : W)));
                         }),
                  out("cells", {rows, 3}, Kind::I32)},
         .run =
             [sample](Backend& be, Bound& t) {
               IRef cells = t.i32(1);
               be.batch_cells(t.i32(0), sample, cells);
             },
         .tol = bits()});
  }
  const Eigen::Vector3d corner(0, 0, 0), outside(4.1, -2.9, 0.3);
  for (const auto& [m, origin] : std::vector<std::pair<int64_t, Eigen::Vector3d>>{
           {0, corner}, {1, corner}, {300, corner}, {300, outside}}) {
    const std::string shapes = "m=" + std::to_string(m) + "," + origin_name(origin);
    all.push_back({.name = "observability_2d/" + shapes,
                   .args = {points_arg(m, grid), out("transmissions", {H, W}, Kind::U32),
                            out("detections", {H, W}, Kind::U32)},
                   .run =
                       [grid, origin](Backend& be, Bound& t) {
                         URef tr = t.u32(1), de = t.u32(2);
                         be.observability_2d(t.f(0), origin, grid, tr, de);
                       },
                   .tol = bits()});
    all.push_back({.name = "occupancy_3d/" + shapes,
                   .args = {points_arg(m, grid), out("probability", {Z, H, W})},
                   .run =
                       [grid, origin](Backend& be, Bound& t) {
                         Ref probability = t.f(1);
                         be.occupancy_3d(t.f(0), origin, grid, probability);
                       },
                   .tol = bits()});
  }
  for (const int64_t m : {0, 1, 300}) {
    all.push_back({.name = "grid_map_features/m=" + std::to_string(m),
                   .args = {points_arg(m, grid), counts_arg("detections", {H, W}, 40),
                            counts_arg("transmissions", {H, W}, 1000), out("layers", {6, H, W})},
                   .run =
                       [grid](Backend& be, Bound& t) {
                         Ref layers = t.f(3);
                         be.grid_map_features(t.f(0), grid, t.u32(1), t.u32(2), layers);
                       },
                   .tol = bits()});
  }
  // Counts up to 2^31 (a sum near the top of uint32), and a 1 x 1 grid; out (H, W) or (1, H, W).
  for (const Shape& cells : std::vector<Shape>{{1, 1}, {11, 15}}) {
    for (const bool planar : {false, true}) {
      Shape out_shape = cells;
      if (planar) out_shape.insert(out_shape.begin(), 1);
      all.push_back({.name = "observability_input/cells=" + shape_name(cells) +
                             ",out=" + shape_name(out_shape),
                     .args = {counts_arg("transmissions", cells, 1u << 31),
                              counts_arg("detections", cells, 1000), out("input", out_shape)},
                     .run =
                         [](Backend& be, Bound& t) {
                           Ref input = t.f(2);
                           be.observability_input(t.u32(0), t.u32(1), input);
                         },
                     .tol = bits()});
    }
  }
  for (const int64_t planes : {0, 3}) {
    std::vector<Arg> args = {counts_arg("transmissions", {H, W}, 5),
                             counts_arg("detections", {H, W}, 5), labels_arg({H, W}, Role::InOut)};
    if (planes > 0) args.push_back(inout_f("probabilities", {planes, H, W}, 0, 1));
    all.push_back({.name = "mask_unobserved/probability_planes=" + std::to_string(planes),
                   .args = args,
                   .run =
                       [planes](Backend& be, Bound& t) {
                         LRef labels = t.u8(2);
                         Ref probabilities = planes > 0 ? t.f(3) : Ref{};
                         be.mask_unobserved(t.u32(0), t.u32(1), labels,
                                            planes > 0 ? &probabilities : nullptr);
                       },
                   .tol = bits()});
  }
}

void add_half_ops(std::vector<Case>& all, Precision p) {
  const std::string d = precision_name(p);
  const double ulp = half_ulp(p);
  // convert: random values, and at the start the rounding's edge cases.
  for (const Shape& x : std::vector<Shape>{{0, 3, 4, 5}, {1, 1, 1, 1}, {2, 3, 5, 7}}) {
    Arg in = in_f("x", x, -4, 4);
    in.fill = [](Rng& rng, void* dst, int64_t n) {
      const float special[] = {std::numeric_limits<float>::quiet_NaN(),
                               std::numeric_limits<float>::infinity(),
                               -std::numeric_limits<float>::infinity(),
                               -0.0f,
                               65504.0f,
                               65519.0f,
                               65520.0f,
                               -1e6f,
                               3.0e38f,
                               6.0e-8f,
                               2.98e-8f,
                               1e-7f,
                               -3e-6f,
                               1.0f + 0x1p-8f,
                               1.0f + 3 * 0x1p-8f,
                               1.0f + 0x1p-11f,
                               1.0f + 3 * 0x1p-11f,
                               1e-40f};
      float* f = static_cast<float*>(dst);
      for (int64_t i = 0; i < n; ++i)
        f[i] = i < static_cast<int64_t>(std::size(special))
                   ? special[i]
                   : static_cast<float>(rng.uniform(-4, 4));
    };
    all.push_back({.name = "convert/" + d + ",x=" + shape_name(x),
                   .args = {in, out("y", x, Kind::H16)},
                   .run =
                       [p](Backend& be, Bound& t) {
                         be.convert(t.f(0), t.tensor(1, p));
                       },
                   .tol = bits(),
                   .precision = p,
                   .reference =
                       [p](Bound& t) {
                         HRef y = t.h16(1);
                         const Ref values = t.f(0);
                         for (int64_t i = 0; i < values.numel(); ++i)
                           y.data[i] = to_bits(values.data[i], p);
                       }});
  }
  for (const Shape& x : std::vector<Shape>{{1, 1, 2, 2}, {2, 3, 7, 9}}) {
    const Shape y = op::maxpool2d(x);
    all.push_back({.name = "maxpool2d_forward/" + d + ",x=" + shape_name(x),
                   .args = {with_nan_and_ties(in_h("x", x, p), p), out("y", y, Kind::H16)},
                   .run =
                       [p](Backend& be, Bound& t) {
                         be.maxpool2d_forward(t.tensor(0, p), t.tensor(1, p), nullptr);
                       },
                   .tol = bits(),
                   .precision = p,
                   .reference =
                       [p](Bound& t) {
                         Tensor<float> pooled;
                         host::maxpool2d_forward(decoded(t.h16(0), p), pooled, nullptr);
                         HRef yy = t.h16(1);
                         encode(pooled, p, yy);
                       }});
  }
  // Bilinear x2 in FP32, rounded once: the host's FP32 taps and the kernel's may round the FP32
  // value differently in its last bit, which can move the 16-bit result by one unit; where the
  // taps cancel (a result near 0 from inputs of either sign in [-1, 1]) that last bit is the
  // inputs' (2^-24 each), not the result's: the atol.
  for (const Shape& x : std::vector<Shape>{{1, 1, 1, 1}, {2, 3, 5, 4}}) {
    const Shape y = op::upsample_bilinear(x);
    all.push_back({.name = "upsample_bilinear_forward/" + d + ",x=" + shape_name(x),
                   .args = {in_h("x", x, p), out("y", y, Kind::H16)},
                   .run =
                       [p](Backend& be, Bound& t) {
                         be.upsample_bilinear_forward(t.tensor(0, p), t.tensor(1, p));
                       },
                   .tol = within(0x1p-22, ulp),
                   .precision = p,
                   .reference =
                       [p](Bound& t) {
                         Tensor<float> up;
                         host::upsample_bilinear_forward(decoded(t.h16(0), p), up);
                         HRef yy = t.h16(1);
                         encode(up, p, yy);
                       }});
  }
  for (const auto& [skip, up] :
       std::vector<std::pair<Shape, Shape>>{{{2, 3, 6, 8}, {2, 4, 6, 8}},
                                            {{1, 2, 7, 9}, {1, 3, 6, 8}},
                                            {{1, 1, 1, 1}, {1, 1, 1, 1}}}) {
    const Shape y = op::pad_concat(skip, up);
    all.push_back(
        {.name = "pad_concat_forward/" + d + ",skip=" + shape_name(skip) + ",up=" + shape_name(up),
         .args = {in_h("skip", skip, p), in_h("up", up, p), out("y", y, Kind::H16)},
         .run =
             [p](Backend& be, Bound& t) { be.pad_concat_forward(t.tensor(0, p), t.tensor(1, p), t.tensor(2, p)); },
         .tol = bits(),
         .precision = p,
         .reference =
             [p](Bound& t) {
               Tensor<float> joined;
               host::pad_concat_forward(decoded(t.h16(0), p), decoded(t.h16(1), p), joined);
               HRef yy = t.h16(2);
               encode(joined, p, yy);
             }});
  }
  all.push_back({.name = "copy_channels/" + d + ",x=2x3x4x5,y=2x8x4x5,c0=4",
                 .args = {in_h("x", {2, 3, 4, 5}, p), inout_h("y", {2, 8, 4, 5}, p)},
                 .run =
                     [p](Backend& be, Bound& t) { be.copy_channels(t.tensor(0, p), 4, t.tensor(1, p)); },
                 .tol = bits(),
                 .precision = p,
                 .reference =
                     [](Bound& t) {
                       const HRef x = t.h16(0);
                       HRef y = t.h16(1);
                       for (int64_t b = 0; b < 2; ++b)
                         std::memcpy(y.data + (b * 8 + 4) * 20, x.data + b * 3 * 20,
                                     3 * 20 * sizeof(uint16_t));
                     }});
  // The band [2, 2 + C) of the canvas zeroed, then each live row's features rounded at its cell.
  for (const auto& [pillars, c] :
       std::vector<std::pair<int64_t, int64_t>>{{0, 4}, {1, 4}, {37, 16}}) {
    const int64_t b = 2, h = 6, w = 7, cc = c + 3;
    all.push_back(
        {.name = "scatter_forward/" + d + ",features=" + std::to_string(pillars) + "x" +
                 std::to_string(c) + ",canvas=" + shape_name({b, cc, h, w}),
         .args = {in_f("features", {pillars, c}, -3, 3),
                  cells_arg(pillars, b, h, w, /*inert=*/true), inout_h("canvas", {b, cc, h, w}, p)},
         .run =
             [p](Backend& be, Bound& t) {
               be.scatter_forward(t.f(0), t.i32(1), 2, t.tensor(2, p));
             },
         .tol = bits(),
         .precision = p,
         .reference =
             [p, c, h, w, cc](Bound& t) {
               const Ref features = t.f(0);
               const IRef cells = t.i32(1);
               HRef canvas = t.h16(2);
               for (int64_t s = 0; s < b; ++s)
                 std::fill_n(canvas.data + (s * cc + 2) * h * w, c * h * w, uint16_t{0});
               for (int64_t r = 0; r < features.dim(0); ++r) {
                 const int32_t* cell = cells.data + 3 * r;
                 if (cell[0] < 0) continue;
                 for (int64_t k = 0; k < c; ++k)
                   canvas.data[((cell[0] * cc + 2 + k) * h + cell[1]) * w + cell[2]] =
                       to_bits(features.data[r * c + k], p);
               }
             }});
  }
  // Weight preparation: bias and BatchNorm folded, bias alone, neither. The 16-bit weights are
  // one product rounded, bit for bit; bias_out = s bias + (beta - s mean) may be two FMAs on a
  // GPU where the host rounds four times: within an FP32 unit or two (of beta where s mean
  // cancels it).
  const Tolerance folded_bias = within(1e-7, 0x1p-22);
  for (const auto& [w, folded] : std::vector<std::pair<Shape, int>>{
           {{4, 3, 3, 3}, 2}, {{33, 17, 3, 3}, 1}, {{12, 6, 1, 1}, 0}, {{1, 40, 1, 1}, 2}}) {
    const Shape w16 = op::half16_conv_weights(w, false);
    std::vector<Arg> args = {in_f("w", w), in_f("bias", {w[0]})};
    add_bn(args, w[0], false, false);
    args.push_back(out("w16", w16, Kind::H16));
    args.push_back(out("bias_out", {w[0]}));
    args.back().tol = folded_bias;
    const bool with_bias = folded >= 1, with_bn = folded == 2;
    all.push_back({.name = "prepare_conv_weights/" + d + ",w=" + shape_name(w) +
                           (with_bias ? ",bias" : "") + (with_bn ? ",batchnorm" : ""),
                   .args = args,
                   .run =
                       [p, with_bias, with_bn](Backend& be, Bound& t) {
                         const Ref bias = t.f(1);
                         const BatchNormRefs bn = t.bn(2, false);
                         Ref bias_out = t.f(7);
                         be.prepare_conv_weights(t.f(0), with_bias ? &bias : nullptr,
                                                 with_bn ? &bn : nullptr, t.tensor(6, p), bias_out,
                                                 TensorRef{});
                       },
                   .tol = bits(),
                   .precision = p,
                   .reference =
                       [p, with_bias, with_bn](Bound& t) {
                         const Ref bias = t.f(1);
                         const BatchNormRefs bn = t.bn(2, false);
                         HRef w16r = t.h16(6);
                         Ref bias_out = t.f(7);
                         define_prepare_conv_weights(t.f(0), with_bias ? &bias : nullptr,
                                                     with_bn ? &bn : nullptr, p, w16r, bias_out);
                       }});
  }
  for (const auto& [w, with_bias] : std::vector<std::pair<Shape, bool>>{
           {{6, 3, 2, 2}, true}, {{16, 8, 2, 2}, false}, {{33, 5, 2, 2}, true}}) {
    const Shape w16 = op::half16_conv_weights(w, true);
    all.push_back({.name = "prepare_conv_transpose_weights/" + d + ",w=" + shape_name(w) +
                           (with_bias ? ",bias" : ""),
                   .args = {in_f("w", w), in_f("bias", {w[1]}), out("w16", w16, Kind::H16),
                            out("bias_out", {4 * w[1]})},
                   .run =
                       [p, with_bias](Backend& be, Bound& t) {
                         const Ref bias = t.f(1);
                         Ref bias_out = t.f(3);
                         be.prepare_conv_transpose_weights(t.f(0), with_bias ? &bias : nullptr,
                                                           t.tensor(2, p), bias_out);
                       },
                   .tol = bits(),
                   .precision = p,
                   .reference =
                       [p, with_bias](Bound& t) {
                         const Ref bias = t.f(1);
                         HRef w16r = t.h16(2);
                         Ref bias_out = t.f(3);
                         define_prepare_conv_transpose_weights(t.f(0), with_bias ? &bias : nullptr,
                                                               p, w16r, bias_out);
                       }});
  }
  // The convolutions: the weights prepared (BatchNorm folded) by the backend itself, then the
  // forward; x and y FP32 or 16-bit. FP32 y: the FP32 sums' rounding (a reduction); 16-bit y: at
  // most one unit of the output's rounding apart. The CPU backend's BF16 3x3 pad-1 convolutions
  // run Winograd F(2x2, 3x3) with the transformed weights and inputs rounded to BF16, within
  // about 2^-7 of the transformed products' magnitudes (test_cpu_bf16 checks that bound element
  // by element): its own NMSE bound.
  struct Conv {
    Shape x, w;
    int pad;
    bool x_half, y_half, relu;
  };
  for (const Conv& cv : std::vector<Conv>{{{2, 3, 7, 5}, {4, 3, 3, 3}, 1, false, false, true},
                                          {{1, 17, 9, 11}, {33, 17, 3, 3}, 1, true, true, true},
                                          {{2, 6, 5, 4}, {12, 6, 1, 1}, 0, true, false, false},
                                          {{1, 2, 5, 5}, {3, 2, 3, 3}, 0, false, true, false},
                                          {{1, 40, 1, 1}, {5, 40, 1, 1}, 0, true, true, true}}) {
    const Shape y = op::conv2d(cv.x, cv.w, cv.pad), w16 = op::half16_conv_weights(cv.w, false);
    std::vector<Arg> args = {cv.x_half ? in_h("x", cv.x, p, -2, 2) : in_f("x", cv.x, -2, 2),
                             in_f("w", cv.w, -0.5, 0.5), in_f("bias", {cv.w[0]})};
    add_bn(args, cv.w[0], false, false);
    args.push_back(out("w16", w16, Kind::H16));
    args.back().tol = bits();
    args.push_back(out("bias_out", {cv.w[0]}));
    args.back().tol = folded_bias;
    args.push_back(out("y", y, cv.y_half ? Kind::H16 : Kind::F32));
    const Conv c = cv;
    const bool winograd = op::winograd_3x3(cv.w, cv.pad);
    all.push_back(
        {.name = "conv2d_prepared_forward/" + d + ",x=" + shape_name(cv.x) + (cv.x_half ? "h" : "f") +
                 ",w=" + shape_name(cv.w) + ",pad=" + std::to_string(cv.pad) +
                 ",y=" + (cv.y_half ? "h" : "f") + (cv.relu ? ",relu" : ""),
         .args = args,
         .run =
             [p, c](Backend& be, Bound& t) {
               const Ref bias = t.f(2);
               const BatchNormRefs bn = t.bn(3, false);
               Ref bias_out = t.f(8);
               const BackendScratch transformed(
                   be, be.prepared_conv_transform_elements(c.w, c.pad, dtype_of(p)));
               be.prepare_conv_weights(t.f(1), &bias, &bn, t.tensor(7, p), bias_out, transformed.tensor(p));
               be.conv2d_prepared_forward(t.tensor(0, p), t.tensor(7, p), transformed.tensor(p), bias_out, c.w,
                                          c.pad, c.relu, t.tensor(9, p));
             },
         .tol = cv.y_half ? within(1e-6, ulp) : nmse_within(1e-12),
         .precision = p,
         .reference =
             [p, c](Bound& t) {
               const Ref bias = t.f(2);
               const BatchNormRefs bn = t.bn(3, false);
               HRef w16r = t.h16(7);
               Ref bias_out = t.f(8);
               define_prepare_conv_weights(t.f(1), &bias, &bn, p, w16r, bias_out);
               define_conv2d_half_forward(t.act(0), w16r, bias_out, c.w, c.pad, c.relu, p,
                                          t.act(9));
             },
         .cpu_tol = winograd ? std::optional<Tolerance>(nmse_within(1e-4)) : std::nullopt});
  }
  // FP32 prepared weights on 16-bit activations (the INT8 forward's head, a 1 x 1 convolution):
  // the weights folded in FP32 (the CPU folds the BatchNorm scale in double, a GPU in FP32: an
  // FP32 unit or two), then FP32 sums of the widened x. The CUDA backend runs them without ReLU
  // into an FP32 y only; the CPU backend also with ReLU into a 16-bit y (BF16 only: its FP32
  // kernels take no FP16).
  struct Pointwise {
    Shape x, w;
    bool relu, y_half;
  };
  for (const Pointwise& cv : std::vector<Pointwise>{{{2, 6, 5, 4}, {12, 6, 1, 1}, false, false},
                                                    {{1, 40, 23, 29}, {13, 40, 1, 1}, false, false},
                                                    {{1, 17, 3, 37}, {7, 17, 1, 1}, true, true}}) {
    if (cv.relu && p != Precision::BF16) continue;  // no backend runs it
    const Shape y = op::conv2d(cv.x, cv.w, 0);
    std::vector<Arg> args = {in_h("x", cv.x, p, -2, 2), in_f("w", cv.w, -0.5, 0.5), in_f("bias", {cv.w[0]})};
    add_bn(args, cv.w[0], false, false);
    args.push_back(out("folded", cv.w));
    args.back().tol = within(1e-7, 0x1p-21);
    args.push_back(out("bias_out", {cv.w[0]}));
    args.back().tol = folded_bias;
    args.push_back(out("y", y, cv.y_half ? Kind::H16 : Kind::F32));
    const Pointwise c = cv;
    all.push_back(
        {.name = "conv2d_prepared_forward/f32_weights," + d + ",x=" + shape_name(cv.x) + ",w=" + shape_name(cv.w) +
                 ",y=" + (cv.y_half ? "h" : "f") + (cv.relu ? ",relu" : ""),
         .args = args,
         .run =
             [p, c](Backend& be, Bound& t) {
               const Ref bias = t.f(2);
               const BatchNormRefs bn = t.bn(3, false);
               Ref bias_out = t.f(8);
               const TensorRef folded = t.tensor(7, p);
               be.prepare_conv_weights(t.f(1), &bias, &bn, folded, bias_out, TensorRef{});
               be.conv2d_prepared_forward(t.tensor(0, p), folded, TensorRef{}, bias_out, c.w, 0, c.relu,
                                          t.tensor(9, p));
             },
         .tol = cv.y_half ? within(1e-6, ulp) : nmse_within(1e-12),
         .precision = p,
         .reference =
             [p, c](Bound& t) {
               const Ref w = t.f(1), bias = t.f(2), folded = t.f(7), bias_out = t.f(8);
               const BatchNormRefs bn = t.bn(3, false);
               const int64_t O = c.w[0], I = c.w[1], B = c.x[0], P = c.x[2] * c.x[3];
               for (int64_t o = 0; o < O; ++o) {
                 const double s = bn.gamma.data[o] / std::sqrt(double{bn.running_var.data[o]} + bn.eps);
                 for (int64_t i = 0; i < I; ++i) folded.data[o * I + i] = static_cast<float>(w.data[o * I + i] * s);
                 bias_out.data[o] =
                     static_cast<float>(s * bias.data[o] + (bn.beta.data[o] - s * bn.running_mean.data[o]));
               }
               const std::vector<double> xv = rounded_activation(t.act(0), p);
               const ActRef yr = t.act(9);
               for (int64_t b = 0; b < B; ++b)
                 for (int64_t o = 0; o < O; ++o)
                   for (int64_t q = 0; q < P; ++q) {
                     double sum = bias_out.data[o];
                     for (int64_t i = 0; i < I; ++i)
                       sum += double{folded.data[o * I + i]} * xv[static_cast<size_t>((b * I + i) * P + q)];
                     store(yr, (b * O + o) * P + q, c.relu ? std::max(sum, 0.0) : sum, p);
                   }
             },
         .runs_on =
             [c, p](const Backend& be, std::string& why) {
               if (be.device() == Device::Cpu) {
                 why = "the CPU's FP32 kernels take bf16 activations, not fp16";
                 return p == Precision::BF16;
               }
               why = "the CUDA backend's FP32 prepared weights run without ReLU into an f32 y";
               return !c.relu && !c.y_half;
             }});
  }
  struct ConvT {
    Shape x;
    int64_t o;
    bool x_half, y_half;
  };
  for (const ConvT& cv : std::vector<ConvT>{{{2, 6, 3, 4}, 3, false, false},
                                            {{1, 16, 5, 7}, 8, true, true},
                                            {{1, 40, 2, 3}, 5, true, false},
                                            {{1, 1, 1, 1}, 1, false, true}}) {
    const Shape w{cv.x[1], cv.o, 2, 2}, y{cv.x[0], cv.o, 2 * cv.x[2], 2 * cv.x[3]};
    std::vector<Arg> args = {cv.x_half ? in_h("x", cv.x, p, -2, 2) : in_f("x", cv.x, -2, 2),
                             in_f("w", w, -0.5, 0.5),
                             in_f("bias", {cv.o}),
                             out("w16", op::half16_conv_weights(w, true), Kind::H16),
                             out("bias_out", {4 * cv.o}),
                             out("y", y, cv.y_half ? Kind::H16 : Kind::F32)};
    args[3].tol = args[4].tol = bits();
    all.push_back(
        {.name = "conv_transpose2d_prepared_forward/" + d + ",x=" + shape_name(cv.x) +
                 (cv.x_half ? "h" : "f") + ",w=" + shape_name(w) + ",y=" + (cv.y_half ? "h" : "f"),
         .args = args,
         .run =
             [p, w](Backend& be, Bound& t) {
               const Ref bias = t.f(2);
               Ref bias_out = t.f(4);
               be.prepare_conv_transpose_weights(t.f(1), &bias, t.tensor(3, p), bias_out);
               be.conv_transpose2d_prepared_forward(t.tensor(0, p), t.tensor(3, p), bias_out, w, t.tensor(5, p));
             },
         .tol = cv.y_half ? within(1e-6, ulp) : nmse_within(1e-12),
         .precision = p,
         .reference =
             [p, w](Bound& t) {
               const Ref bias = t.f(2);
               HRef w16r = t.h16(3);
               Ref bias_out = t.f(4);
               define_prepare_conv_transpose_weights(t.f(1), &bias, p, w16r, bias_out);
               define_conv_transpose2d_half_forward(t.act(0), w16r, bias_out, w, p, t.act(5));
             }});
  }
  // The 16-bit training gradients: the FP32 backward of the operands rounded to p, dbias of the
  // FP32 dy; for the first shape also dw alone (the first layer's).
  for (const auto& [x, w, pad] :
       std::vector<std::tuple<Shape, Shape, int>>{{{2, 3, 7, 5}, {4, 3, 3, 3}, 1},
                                                  {{1, 17, 9, 11}, {33, 17, 3, 3}, 1},
                                                  {{2, 6, 5, 4}, {12, 6, 1, 1}, 0}}) {
    const Shape y = op::conv2d(x, w, pad);
    for (const bool full : {true, false}) {
      if (!full && x[1] != 3) continue;
      std::vector<Arg> args = {in_f("x", x), in_f("w", w), in_f("dy", y), out("dw", w)};
      if (full) args.push_back(out("dx", x)), args.push_back(out("dbias", {w[0]}));
      all.push_back({.name = "conv2d_backward/" + d + (full ? "," : ",dw_only,") + "x=" +
                             shape_name(x) + ",w=" + shape_name(w) + ",pad=" + std::to_string(pad),
                     .args = args,
                     .run =
                         [p, pad, full](Backend& be, Bound& t) {
                           Ref dw = t.f(3), dx = full ? t.f(4) : Ref{}, db = full ? t.f(5) : Ref{};
                           be.conv2d_backward(t.f(0), t.f(1), t.f(2), pad, full ? &dx : nullptr, dw,
                                              full ? &db : nullptr, dtype_of(p));
                         },
                     .tol = nmse_within(1e-12),
                     .precision = p,
                     .training = true,
                     .reference =
                         [p, pad, full](Bound& t) {
                           Tensor<float> dw = Tensor<float>::view(t.f(3).data, t.f(3).shape), dx;
                           if (full) dx = Tensor<float>::view(t.f(4).data, t.f(4).shape);
                           host::conv2d_backward(rounded_copy(t.f(0), p), rounded_copy(t.f(1), p),
                                                 rounded_copy(t.f(2), p), pad, full ? &dx : nullptr,
                                                 &dw, nullptr);
                           if (!full) return;
                           Ref db = t.f(5);
                           define_bias_gradient(t.f(2), db);
                         }});
    }
  }
  for (const auto& [x, o] :
       std::vector<std::pair<Shape, int64_t>>{{{2, 6, 3, 4}, 3}, {{1, 16, 5, 7}, 8}}) {
    const Shape w{x[1], o, 2, 2}, y{x[0], o, 2 * x[2], 2 * x[3]};
    all.push_back({.name = "conv_transpose2d_backward/" + d + ",x=" + shape_name(x) +
                           ",o=" + std::to_string(o),
                   .args = {in_f("x", x), in_f("w", w), in_f("dy", y), out("dx", x), out("dw", w),
                            out("dbias", {o})},
                   .run =
                       [p](Backend& be, Bound& t) {
                         Ref dx = t.f(3), dw = t.f(4), db = t.f(5);
                         be.conv_transpose2d_backward(t.f(0), t.f(1), t.f(2), dx, dw, &db, dtype_of(p));
                       },
                   .tol = nmse_within(1e-12),
                   .precision = p,
                   .training = true,
                   .reference =
                       [p](Bound& t) {
                         Tensor<float> dx = Tensor<float>::view(t.f(3).data, t.f(3).shape),
                                       dw = Tensor<float>::view(t.f(4).data, t.f(4).shape);
                         host::conv_transpose2d_backward(
                             rounded_copy(t.f(0), p), rounded_copy(t.f(1), p),
                             rounded_copy(t.f(2), p), &dx, &dw, nullptr);
                         Ref db = t.f(5);
                         define_bias_gradient(t.f(2), db);
                       }});
  }
}

// An INT8 convolution's input x (FP32, or BF16 where `half`) for the input scale sx: uniform in
// [lo sx, hi sx) (past the clamps where lo or hi lie beyond 127, 255 or below 0), and at fixed
// positions the rule's edge cases: NaN, +-Inf, half-integer multiples (k + 1/2) sx, |k| < 128
// (ties to even where sx is a power of two; k + 1/2 fits BF16), and, in FP32, the same one or two
// units in the last place apart (where x r and x / sx may round to different integers: the rule
// multiplies).
Arg int8_input(Shape shape, bool half, float sx, double lo, double hi) {
  Arg a{"x", std::move(shape), half ? Kind::H16 : Kind::F32, Role::Input, {}};
  a.fill = [half, sx, lo, hi](Rng& rng, void* dst, int64_t n) {
    const float inf = std::numeric_limits<float>::infinity();
    for (int64_t i = 0; i < n; ++i) {
      float v = static_cast<float>(rng.uniform(lo, hi)) * sx;
      if (i % 17 == 3)
        v = std::numeric_limits<float>::quiet_NaN();
      else if (i % 19 == 5)
        v = inf;
      else if (i % 23 == 7)
        v = -inf;
      else if (i % 5 == 2 || i % 7 == 4) {
        const double k = std::floor(rng.uniform(std::max(lo, -127.0), std::min(hi, 127.0)));
        v = (static_cast<float>(k) + 0.5f) * sx;
        if (i % 5 != 2) {
          const float toward = rng.uniform_int(2) == 0 ? -inf : inf;
          for (uint64_t u = 1 + rng.uniform_int(2); u > 0; --u) v = std::nextafter(v, toward);
        }
      }
      if (half)
        static_cast<uint16_t*>(dst)[i] = weights::float_to_bf16_bits(v);
      else
        static_cast<float*>(dst)[i] = v;
    }
  };
  return a;
}
// w (O, ...) with output channel o's weights all 0 (its scale 0, its int8 weights 0).
Arg with_zero_channel(Arg w, int64_t o) {
  w.fill = [fill = w.fill, o, per = shape_numel(w.shape) / w.shape.at(0)](Rng& rng, void* dst,
                                                                           int64_t n) {
    fill(rng, dst, n);
    std::fill_n(static_cast<float*>(dst) + o * per, per, 0.0f);
  };
  return w;
}

// The INT8 convolutions (DESIGN.md section 10): weights prepared as I8 with their weight_scale,
// then the forward with x quantized by an Int8Input, signed or non-negative; x and y FP32 or BF16.
// Integer sums and one epilogue: every output bit for bit.
void add_int8_ops(std::vector<Case>& all) {
  const Precision p = Precision::I8;
  // Weight preparation: bias and BatchNorm folded, bias alone, neither (with an all-zero output
  // channel); bias_out as the 16-bit cases' (FMAs on a GPU).
  const Tolerance folded_bias = within(1e-7, 0x1p-22);
  for (const auto& [w, folded] : std::vector<std::pair<Shape, int>>{
           {{4, 3, 3, 3}, 2}, {{33, 17, 3, 3}, 1}, {{12, 6, 1, 1}, 0}}) {
    const bool with_bias = folded >= 1, with_bn = folded == 2, zero_channel = folded == 0;
    std::vector<Arg> args = {zero_channel ? with_zero_channel(in_f("w", w), 5) : in_f("w", w),
                             in_f("bias", {w[0]})};
    add_bn(args, w[0], false, false);
    args.push_back(out("w8", op::half16_conv_weights(w, false), Kind::I8));
    args.push_back(out("weight_scale", {w[0]}));
    args.push_back(out("bias_out", {w[0]}));
    args.back().tol = folded_bias;
    all.push_back({.name = "prepare_conv_weights/int8,w=" + shape_name(w) +
                           (with_bias ? ",bias" : "") + (with_bn ? ",batchnorm" : "") +
                           (zero_channel ? ",zero_channel" : ""),
                   .args = args,
                   .run =
                       [p, with_bias, with_bn](Backend& be, Bound& t) {
                         const Ref bias = t.f(1), weight_scale = t.f(7);
                         const BatchNormRefs bn = t.bn(2, false);
                         Ref bias_out = t.f(8);
                         be.prepare_conv_weights(t.f(0), with_bias ? &bias : nullptr,
                                                 with_bn ? &bn : nullptr, t.tensor(6, p), bias_out,
                                                 TensorRef{}, &weight_scale);
                       },
                   .tol = bits(),
                   .precision = p,
                   .reference =
                       [with_bias, with_bn](Bound& t) {
                         const Ref bias = t.f(1);
                         const BatchNormRefs bn = t.bn(2, false);
                         RefT<int8_t> w8 = t.i8(6);
                         Ref weight_scale = t.f(7), bias_out = t.f(8);
                         define_prepare_int8_conv_weights(t.f(0), with_bias ? &bias : nullptr,
                                                          with_bn ? &bn : nullptr, w8,
                                                          weight_scale, bias_out);
                       }});
  }
  for (const auto& [w, with_bias] :
       std::vector<std::pair<Shape, bool>>{{{6, 3, 2, 2}, true}, {{33, 5, 2, 2}, false}}) {
    all.push_back({.name = "prepare_conv_transpose_weights/int8,w=" + shape_name(w) +
                           (with_bias ? ",bias" : ""),
                   .args = {in_f("w", w), in_f("bias", {w[1]}),
                            out("w8", op::half16_conv_weights(w, true), Kind::I8),
                            out("weight_scale", {4 * w[1]}), out("bias_out", {4 * w[1]})},
                   .run =
                       [p, with_bias](Backend& be, Bound& t) {
                         const Ref bias = t.f(1), weight_scale = t.f(3);
                         Ref bias_out = t.f(4);
                         be.prepare_conv_transpose_weights(t.f(0), with_bias ? &bias : nullptr,
                                                           t.tensor(2, p), bias_out, &weight_scale);
                       },
                   .tol = bits(),
                   .precision = p,
                   .reference =
                       [with_bias](Bound& t) {
                         const Ref bias = t.f(1);
                         RefT<int8_t> w8 = t.i8(2);
                         Ref weight_scale = t.f(3), bias_out = t.f(4);
                         define_prepare_int8_conv_transpose_weights(
                             t.f(0), with_bias ? &bias : nullptr, w8, weight_scale, bias_out);
                       }});
  }
  // The convolutions, on weights the backend prepared itself (BatchNorm folded): a 3x3 pad 1 with
  // ReLU on a non-negative x reaching past 127 sx and 255 sx (and a few negatives, quantized to
  // 0); a 3x3 on a signed x past +-127 sx, 17 input channels (K padded to 32 per tap); a 1x1 of 40
  // channels with an all-zero output channel. The bias and the BatchNorm's mean are 0 here, so
  // that bias_out = beta whether or not the backend fuses s bias + beta - s mean into FMAs, and y
  // compares bit for bit (the folding itself: prepare_conv_weights/int8 above).
  struct Conv {
    Shape x, w;
    int pad;
    bool x_half, y_half, relu, non_negative;
    float sx;
    double lo, hi;  // x's range in units of sx
  };
  for (const Conv& cv : std::vector<Conv>{
           {{2, 3, 7, 5}, {4, 3, 3, 3}, 1, false, true, true, true, 0x1p-6f, -20, 300},
           {{1, 17, 6, 7}, {9, 17, 3, 3}, 1, false, true, false, false, 0.0137f, -150, 150},
           {{2, 40, 3, 4}, {5, 40, 1, 1}, 0, true, false, true, true, 0x1p-5f, -5, 270}}) {
    const Shape y = op::conv2d(cv.x, cv.w, cv.pad);
    Arg w = in_f("w", cv.w, -0.5, 0.5);
    if (cv.w[2] == 1) w = with_zero_channel(w, 2);
    std::vector<Arg> args = {int8_input(cv.x, cv.x_half, cv.sx, cv.lo, cv.hi), w,
                             in_f("bias", {cv.w[0]}, 0, 0)};
    add_bn(args, cv.w[0], false, false);
    args[5] = in_f("running_mean", {cv.w[0]}, 0, 0);
    args.push_back(out("w8", op::half16_conv_weights(cv.w, false), Kind::I8));
    args.push_back(out("weight_scale", {cv.w[0]}));
    args.push_back(out("bias_out", {cv.w[0]}));
    args.push_back(out("y", y, cv.y_half ? Kind::H16 : Kind::F32));
    const Conv c = cv;
    all.push_back(
        {.name = "conv2d_prepared_forward/int8,x=" + shape_name(cv.x) + (cv.x_half ? "h" : "f") +
                 ",w=" + shape_name(cv.w) + ",pad=" + std::to_string(cv.pad) +
                 ",y=" + (cv.y_half ? "h" : "f") + (cv.relu ? ",relu" : "") +
                 (cv.non_negative ? ",non_negative" : ",signed"),
         .args = args,
         .run =
             [p, c](Backend& be, Bound& t) {
               const Ref bias = t.f(2), weight_scale = t.f(8);
               const BatchNormRefs bn = t.bn(3, false);
               Ref bias_out = t.f(9);
               be.prepare_conv_weights(t.f(1), &bias, &bn, t.tensor(7, p), bias_out, TensorRef{},
                                       &weight_scale);
               be.conv2d_prepared_forward(t.tensor(0, p), t.tensor(7, p), TensorRef{}, bias_out,
                                          c.w, c.pad, c.relu, t.tensor(10, p), &weight_scale,
                                          Int8Input{c.sx, c.non_negative});
             },
         .tol = bits(),
         .precision = p,
         .reference =
             [c](Bound& t) {
               const Ref bias = t.f(2);
               const BatchNormRefs bn = t.bn(3, false);
               RefT<int8_t> w8 = t.i8(7);
               Ref weight_scale = t.f(8), bias_out = t.f(9);
               define_prepare_int8_conv_weights(t.f(1), &bias, &bn, w8, weight_scale, bias_out);
               define_int8_conv2d_forward(t.act(0), w8, weight_scale, bias_out, c.w, c.pad, c.relu,
                                          Int8Input{c.sx, c.non_negative}, t.act(10));
             }});
  }
  // The transposed 2x2 in both modes; 40 input channels (K padded to 64).
  struct ConvT {
    Shape x;
    int64_t o;
    bool x_half, y_half, non_negative;
    float sx;
    double lo, hi;
  };
  for (const ConvT& cv :
       std::vector<ConvT>{{{1, 6, 3, 4}, 3, false, true, true, 0x1p-4f, -10, 290},
                          {{2, 40, 2, 3}, 5, true, false, false, 0x1p-6f, -150, 150}}) {
    const Shape w{cv.x[1], cv.o, 2, 2}, y{cv.x[0], cv.o, 2 * cv.x[2], 2 * cv.x[3]};
    const Int8Input input{cv.sx, cv.non_negative};
    all.push_back(
        {.name = "conv_transpose2d_prepared_forward/int8,x=" + shape_name(cv.x) +
                 (cv.x_half ? "h" : "f") + ",w=" + shape_name(w) + ",y=" + (cv.y_half ? "h" : "f") +
                 (cv.non_negative ? ",non_negative" : ",signed"),
         .args = {int8_input(cv.x, cv.x_half, cv.sx, cv.lo, cv.hi), in_f("w", w, -0.5, 0.5),
                  in_f("bias", {cv.o}), out("w8", op::half16_conv_weights(w, true), Kind::I8),
                  out("weight_scale", {4 * cv.o}), out("bias_out", {4 * cv.o}),
                  out("y", y, cv.y_half ? Kind::H16 : Kind::F32)},
         .run =
             [p, w, input](Backend& be, Bound& t) {
               const Ref bias = t.f(2), weight_scale = t.f(4);
               Ref bias_out = t.f(5);
               be.prepare_conv_transpose_weights(t.f(1), &bias, t.tensor(3, p), bias_out,
                                                 &weight_scale);
               be.conv_transpose2d_prepared_forward(t.tensor(0, p), t.tensor(3, p), bias_out, w,
                                                    t.tensor(6, p), &weight_scale, input);
             },
         .tol = bits(),
         .precision = p,
         .reference =
             [w, input](Bound& t) {
               const Ref bias = t.f(2);
               RefT<int8_t> w8 = t.i8(3);
               Ref weight_scale = t.f(4), bias_out = t.f(5);
               define_prepare_int8_conv_transpose_weights(t.f(1), &bias, w8, weight_scale,
                                                          bias_out);
               define_int8_conv_transpose2d_forward(t.act(0), w8, weight_scale, bias_out, w, input,
                                                    t.act(6));
             }});
  }
}

// The losses: each kind, the Lovász term at the weight a replica of two gives it.
const LossSpec kLossSpecs[] = {LossSpec(LossKind::CrossEntropy), LossSpec(LossKind::Bce),
                               LossSpec(LossKind::CrossEntropyLovasz, 0.5f)};

std::string loss_case_name(const LossSpec& spec) {
  return spec.kind == LossKind::CrossEntropy ? "ce," : spec.kind == LossKind::Bce ? "bce," : "ce+lovasz,";
}

std::vector<Case> cases() {
  std::vector<Case> all;
  add_input_ops(all);
  // Convolutions: 3x3 pad 1, 1x1 (the head), odd sizes, and channel counts that are not a
  // multiple of a tile; for two shapes also without the optional tensors (no bias; the first
  // layer's backward, dw alone).
  for (const auto& [x, w, pad] :
       std::vector<std::tuple<Shape, Shape, int>>{{{2, 3, 7, 5}, {4, 3, 3, 3}, 1},
                                                  {{1, 8, 6, 6}, {5, 8, 3, 3}, 1},
                                                  {{2, 6, 5, 4}, {12, 6, 1, 1}, 0},
                                                  {{1, 17, 9, 11}, {33, 17, 3, 3}, 1},
                                                  {{1, 2, 5, 5}, {3, 2, 3, 3}, 0}}) {
    const std::string shapes =
        "x=" + shape_name(x) + ",w=" + shape_name(w) + ",pad=" + std::to_string(pad);
    const Shape y{x[0], w[0], x[2] + 2 * pad - w[2] + 1, x[3] + 2 * pad - w[3] + 1};
    for (const bool full : {true, false}) {
      if (!full && x[1] != 3 && x[1] != 6) continue;
      all.push_back({std::string("conv2d_forward/") + (full ? "" : "no_bias,") + shapes,
                     {in_f("x", x), in_f("w", w), in_f("bias", {w[0]}), out("y", y)},
                     [pad, full](Backend& be, Bound& t) {
                       Ref bias = t.f(2), yy = t.f(3);
                       be.conv2d_forward(t.f(0), t.f(1), full ? &bias : nullptr, pad, yy);
                     },
                     nmse_within(1e-11)});
      std::vector<Arg> args = {in_f("x", x), in_f("w", w), in_f("dy", y), out("dw", w)};
      if (full) args.push_back(out("dx", x)), args.push_back(out("dbias", {w[0]}));
      all.push_back({std::string("conv2d_backward/") + (full ? "" : "dw_only,") + shapes, args,
                     [pad, full](Backend& be, Bound& t) {
                       Ref dw = t.f(3), dx = full ? t.f(4) : Ref{}, db = full ? t.f(5) : Ref{};
                       be.conv2d_backward(t.f(0), t.f(1), t.f(2), pad, full ? &dx : nullptr, dw,
                                          full ? &db : nullptr);
                     },
                     nmse_within(1e-11)});
      args = {in_f("x", x), in_f("w", w), in_f("bias", {w[0]})};
      add_bn(args, w[0], false, false);
      args.push_back(out("y", y));
      all.push_back({std::string("conv2d_bn_relu_eval/") + (full ? "" : "no_bias,") + shapes, args,
                     [pad, full](Backend& be, Bound& t) {
                       Ref bias = t.f(2), yy = t.f(7);
                       be.conv2d_bn_relu_eval(t.f(0), t.f(1), full ? &bias : nullptr,
                                              t.bn(3, false), pad, yy);
                     },
                     nmse_within(1e-11)});
    }
  }
  for (const auto& [x, o] :
       std::vector<std::pair<Shape, int64_t>>{{{2, 6, 3, 4}, 3}, {{1, 16, 5, 7}, 8}}) {
    const Shape w{x[1], o, 2, 2}, y{x[0], o, 2 * x[2], 2 * x[3]};
    for (const bool bias : {true, false}) {
      const std::string shapes =
          (bias ? "" : "no_bias,") + ("x=" + shape_name(x) + ",o=" + std::to_string(o));
      all.push_back({"conv_transpose2d_forward/" + shapes,
                     {in_f("x", x), in_f("w", w), in_f("bias", {o}), out("y", y)},
                     [bias](Backend& be, Bound& t) {
                       Ref b = t.f(2), yy = t.f(3);
                       be.conv_transpose2d_forward(t.f(0), t.f(1), bias ? &b : nullptr, yy);
                     }});
      // dy is an input: no backend may change it.
      std::vector<Arg> args = {in_f("x", x), in_f("w", w), in_f("dy", y), out("dx", x),
                               out("dw", w)};
      if (bias) args.push_back(out("dbias", {o}));
      all.push_back({"conv_transpose2d_backward/" + shapes, args, [bias](Backend& be, Bound& t) {
                       Ref dx = t.f(3), dw = t.f(4), db = bias ? t.f(5) : Ref{};
                       be.conv_transpose2d_backward(t.f(0), t.f(1), t.f(2), dx, dw,
                                                    bias ? &db : nullptr);
                     }});
    }
  }
  // BatchNorm + ReLU; training also synchronised over two replicas (TwinStatistics), and the
  // backward in place (dx = dy).
  for (const Shape& x : std::vector<Shape>{{2, 3, 5, 4}, {1, 7, 9, 3}}) {
    const std::string shapes = "x=" + shape_name(x);
    for (const char* mode : {"eval", "train", "train,twin_replicas"}) {
      const bool training = mode[0] == 't';
      const bool twins = std::string_view(mode).ends_with(",twin_replicas");
      std::vector<Arg> args = {in_f("x", x)};
      add_bn(args, x[1], training, training);
      args.push_back(out("y", x));
      const size_t y = args.size() - 1;
      all.push_back({.name = std::string("batchnorm_relu_forward/") + mode + "," + shapes,
                     .args = args,
                     .run =
                         [training, twins, y](Backend& be, Bound& t) {
                           TwinStatistics replicas;
                           BatchNormRefs bn = t.bn(1, training);
                           if (twins) bn.replicas = &replicas;
                           Ref yy = t.f(y);
                           be.batchnorm_relu_forward(t.f(0), bn, training, yy);
                         },
                     .runs_on = twins ? synchronises_batchnorm : nullptr});
    }
    for (const char* mode : {"", "twin_replicas,", "in_place,"}) {
      const bool twins = mode[0] == 't', in_place = mode[0] == 'i';
      std::vector<Arg> args = {in_f("x", x), in_f("y", x, 0, 1),
                               in_place ? inout_f("dy", x) : in_f("dy", x)};
      add_bn(args, x[1], false, false, /*saved_in=*/true);
      if (!in_place) args.push_back(out("dx", x));
      args.push_back(out("dgamma", {x[1]}));
      args.push_back(out("dbeta", {x[1]}));
      const size_t dgamma = args.size() - 2;
      all.push_back({.name = std::string("batchnorm_relu_backward/") + mode + shapes,
                     .args = args,
                     .run =
                         [twins, in_place, dgamma](Backend& be, Bound& t) {
                           TwinStatistics replicas;
                           BatchNormRefs bn = t.bn(3, true);
                           if (twins) bn.replicas = &replicas;
                           Ref dx = in_place ? t.f(2) : t.f(9), dg = t.f(dgamma),
                               db = t.f(dgamma + 1);
                           be.batchnorm_relu_backward(t.f(0), t.f(1), t.f(2), bn, dx, dg, db);
                         },
                     .runs_on = twins ? synchronises_batchnorm : nullptr});
    }
  }
  // Pooling (NaN, -Inf and ties among the inputs), upsampling, joins, channel copies: data
  // movement, exact.
  for (const Shape& x : std::vector<Shape>{{2, 3, 6, 8}, {1, 4, 7, 5}, {1, 1, 2, 2}}) {
    const Shape p{x[0], x[1], x[2] / 2, x[3] / 2};
    all.push_back({"maxpool2d_forward/x=" + shape_name(x),
                   {with_nan_and_ties(in_f("x", x)), out("y", p), out("argmax", p, Kind::I32)},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(1);
                     IRef am = t.i32(2);
                     be.maxpool2d_forward(t.f(0), y, &am);
                   },
                   bits()});
    all.push_back({"maxpool2d_backward/x=" + shape_name(x),
                   {with_nan_and_ties(in_f("x", x)), in_f("dy", p), out("dx", x), out("y", p),
                    out("argmax", p, Kind::I32)},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(3), dx = t.f(2);
                     IRef am = t.i32(4);
                     be.maxpool2d_forward(t.f(0), y, &am);
                     be.maxpool2d_backward(t.f(1), am, dx);
                   },
                   bits()});
  }
  for (const Shape& x : std::vector<Shape>{{2, 3, 6, 8}, {1, 4, 7, 5}, {1, 1, 1, 1}}) {
    const Shape u{x[0], x[1], 2 * x[2], 2 * x[3]};
    all.push_back({"upsample_bilinear_forward/x=" + shape_name(x),
                   {in_f("x", x), out("y", u)},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(1);
                     be.upsample_bilinear_forward(t.f(0), y);
                   },
                   within(1e-7, 0x1p-22)});
    all.push_back({"upsample_bilinear_backward/x=" + shape_name(x),
                   {in_f("dy", u), out("dx", x)},
                   [](Backend& be, Bound& t) {
                     Ref dx = t.f(1);
                     be.upsample_bilinear_backward(t.f(0), dx);
                   },
                   within(1e-6, 1e-6)});
  }
  for (const auto& [skip, up] :
       std::vector<std::pair<Shape, Shape>>{{{2, 3, 6, 8}, {2, 4, 6, 8}},
                                            {{1, 2, 7, 9}, {1, 3, 6, 8}},
                                            {{1, 1, 1, 1}, {1, 1, 1, 1}}}) {
    const Shape y{skip[0], skip[1] + up[1], skip[2], skip[3]};
    const std::string shapes = "skip=" + shape_name(skip) + ",up=" + shape_name(up);
    all.push_back({"pad_concat_forward/" + shapes,
                   {in_f("skip", skip), in_f("up", up), out("y", y)},
                   [](Backend& be, Bound& t) {
                     Ref yy = t.f(2);
                     be.pad_concat_forward(t.f(0), t.f(1), yy);
                   },
                   bits()});
    all.push_back({"pad_concat_backward/" + shapes,
                   {in_f("dy", y), out("dskip", skip), out("dup", up)},
                   [](Backend& be, Bound& t) {
                     Ref ds = t.f(1), du = t.f(2);
                     be.pad_concat_backward(t.f(0), ds, du);
                   },
                   bits()});
  }
  for (const auto& [x, y, c0] : std::vector<std::tuple<Shape, Shape, int>>{
           {{2, 3, 4, 5}, {2, 8, 4, 5}, 4}, {{1, 1, 1, 1}, {1, 2, 1, 1}, 1}}) {
    const std::string shapes =
        "x=" + shape_name(x) + ",y=" + shape_name(y) + ",c0=" + std::to_string(c0);
    all.push_back({"copy_channels/" + shapes,
                   {in_f("x", x), inout_f("y", y)},
                   [c0](Backend& be, Bound& t) {
                     Ref yy = t.f(1);
                     be.copy_channels(t.f(0), c0, yy);
                   },
                   bits()});
    all.push_back({"extract_channels/" + shapes,
                   {in_f("y", y), out("x", x)},
                   [c0](Backend& be, Bound& t) {
                     Ref xx = t.f(1);
                     be.extract_channels(t.f(0), c0, xx);
                   },
                   bits()});
  }
  for (const Shape& x : std::vector<Shape>{{0, 3, 4, 5}, {1, 1, 1, 1}, {2, 3, 4, 5}}) {
    all.push_back({"add_inplace/a=" + shape_name(x),
                   {inout_f("a", x), in_f("b", x)},
                   [](Backend& be, Bound& t) {
                     Ref a = t.f(0);
                     be.add_inplace(a, t.f(1));
                   },
                   bits()});
  }
  // Pillars: PFN forward (eval, training) and backward, scatter and its backward; 70 pillars of
  // 20 points are three of the CPU backend's blocks of 32, the last one short.
  // One pillar of one point in evaluation (training's batch statistics need two values), one
  // pillar of three in training.
  for (const auto& [p, n, c] : std::vector<std::tuple<int64_t, int64_t, int64_t>>{
           {1, 1, 4}, {1, 3, 4}, {5, 3, 4}, {37, 8, 16}, {70, 20, 64}}) {
    const std::string shapes = "points=" + shape_name({p, n, 10}) + ",c=" + std::to_string(c);
    const bool trains = p * n > 1, evaluates = n != 3 || p != 1;
    for (bool training : {false, true}) {
      if (training ? !trains : !evaluates) continue;
      std::vector<Arg> args = {in_f("points", {p, n, 10}), in_f("weight", {c, 10})};
      add_bn(args, c, training, training);
      args.push_back(out("out", {p, c}));
      if (training) args.push_back(out("argmax", {p, c}, Kind::I32));
      const size_t o = 2 + 4 + (training ? 2 : 0);
      all.push_back({std::string("pfn_forward/") + (training ? "train," : "eval,") + shapes, args,
                     [training, o](Backend& be, Bound& t) {
                       BatchNormRefs bn = t.bn(2, training);
                       Ref y = t.f(o);
                       IRef am = training ? t.i32(o + 1) : IRef{};
                       be.pfn_forward(t.f(0), t.f(1), bn, training, IRef{}, am, y);
                     },
                     nmse_within(1e-11)});
    }
    // Evaluation with live rows (a device pipeline's P'): the rows from p / 2 on keep their
    // random contents (the reference leaves them too), the others are computed; a live count
    // past the rows (p + 5) computes every row.
    for (const int64_t live : {p / 2, p + 5}) {
      if (!evaluates) continue;
      std::vector<Arg> eval_args = {in_f("points", {p, n, 10}), in_f("weight", {c, 10})};
      add_bn(eval_args, c, false, false);
      eval_args.push_back(inout_f("out", {p, c}, -9, -8));
      eval_args.push_back(
          in_i32("live_rows", {1}, [live](Rng&, int64_t) { return static_cast<int32_t>(live); }));
      all.push_back({"pfn_forward/eval,live=" + std::to_string(live) + "," + shapes, eval_args,
                     [](Backend& be, Bound& t) {
                       BatchNormRefs bn = t.bn(2, false);
                       Ref y = t.f(6);
                       IRef am;
                       be.pfn_forward(t.f(0), t.f(1), bn, false, t.i32(7), am, y);
                     },
                     nmse_within(1e-11)});
    }
    // The backward after a training forward on the same backend (its arg-max slots), both also
    // synchronised over two replicas.
    for (const bool twins : {false, true}) {
      if (!trains || (twins && p != 37)) continue;
      std::vector<Arg> args = {in_f("points", {p, n, 10}), in_f("weight", {c, 10})};
      add_bn(args, c, true, true);
      for (Arg a : {out("out", {p, c}), out("argmax", {p, c}, Kind::I32)}) args.push_back(a);
      for (Arg a :
           {in_f("dout", {p, c}), out("dweight", {c, 10}), out("dgamma", {c}), out("dbeta", {c})})
        args.push_back(a);
      all.push_back(
          {.name = std::string("pfn_backward/") + (twins ? "twin_replicas," : "") + shapes,
           .args = args,
           .run =
               [twins](Backend& be, Bound& t) {
                 TwinStatistics replicas;
                 BatchNormRefs bn = t.bn(2, true);
                 if (twins) bn.replicas = &replicas;
                 Ref y = t.f(8), dw = t.f(11), dg = t.f(12), db = t.f(13);
                 IRef am = t.i32(9);
                 be.pfn_forward(t.f(0), t.f(1), bn, true, IRef{}, am, y);
                 be.pfn_backward(t.f(0), t.f(1), bn, am, t.f(10), dw, dg, db);
               },
           .tol = nmse_within(1e-11),
           .runs_on = twins ? synchronises_batchnorm : nullptr});
    }
  }
  for (const auto& [p, c] :
       std::vector<std::pair<int64_t, int64_t>>{{0, 4}, {1, 4}, {37, 16}, {70, 64}}) {
    const std::string shapes = "features=" + shape_name({p, c});
    const int64_t b = 2, h = 6, w = 7, cc = c + 3;
    all.push_back(
        {"scatter_forward/" + shapes,
         {in_f("features", {p, c}), cells_arg(p, b, h, w), inout_f("canvas", {b, cc, h, w})},
         [](Backend& be, Bound& t) {
           Ref canvas = t.f(2);
           be.scatter_forward(t.f(0), t.i32(1), 2, canvas);
         },
         bits()});
    all.push_back(
        {"scatter_backward/" + shapes,
         {in_f("dcanvas", {b, cc, h, w}), cells_arg(p, b, h, w), out("dfeatures", {p, c})},
         [](Backend& be, Bound& t) {
           Ref df = t.f(2);
           be.scatter_backward(t.f(0), t.i32(1), 1, df);
         },
         bits()});
  }
  // The head: softmax (per element: its exp and sums round apart by an ulp or two), class map,
  // both losses.
  for (const Shape& logits : std::vector<Shape>{{1, 12, 1, 1}, {1, 12, 4, 5}, {2, 12, 7, 3}}) {
    const std::string shapes = "logits=" + shape_name(logits);
    const Shape map{logits[0], logits[2], logits[3]};
    all.push_back({"softmax/" + shapes,
                   {in_f("logits", logits, -4, 4), out("probs", logits)},
                   [](Backend& be, Bound& t) {
                     Ref probs = t.f(1);
                     be.softmax(t.f(0), probs);
                   },
                   within(1e-12, 2e-6)});
    all.push_back({"argmax/" + shapes,
                   {in_f("logits", logits, -4, 4), out("labels", map, Kind::U8)},
                   [](Backend& be, Bound& t) {
                     LRef labels = t.u8(1);
                     be.argmax(t.f(0), labels);
                   }});
    // Logits up to +-100: exp overflows FP32 unless the largest is subtracted first.
    all.push_back({"softmax/large," + shapes,
                   {in_f("logits", logits, -100, 100), out("probs", logits)},
                   [](Backend& be, Bound& t) {
                     Ref probs = t.f(1);
                     be.softmax(t.f(0), probs);
                   },
                   within(1e-12, 2e-6)});
    for (const LossSpec& spec : kLossSpecs) {
      all.push_back(
          {"loss/" + loss_case_name(spec) + "large," + shapes,
           {in_f("logits", logits, -100, 100), labels_arg(map), in_f("coefficients", {13}, 0.5, 4),
            out("dlogits", logits)},
           [spec](Backend& be, Bound& t) {
             Ref dl = t.f(3);
             t.scalar = be.loss(spec, t.f(0), t.u8(1), t.f(2), dl);
           },
           nmse_within(1e-13),
           true});
    }
    // Logits of three values only: most cells tie, and the first class of the largest wins.
    Arg tied = in_f("logits", logits);
    tied.fill = [](Rng& rng, void* dst, int64_t n) {
      for (int64_t i = 0; i < n; ++i)
        static_cast<float*>(dst)[i] = static_cast<float>(rng.uniform_int(3));
    };
    all.push_back(
        {"argmax/ties," + shapes, {tied, out("labels", map, Kind::U8)}, [](Backend& be, Bound& t) {
           LRef labels = t.u8(1);
           be.argmax(t.f(0), labels);
         }});
    // The test-time flips' ops (ScanSegmenter): a pass's probabilities mirrored back onto the
    // running sum, each mirror; and the class of the largest positive value, where every third
    // cell holds none (0, ties and negative values: class 0) and NaN, never the largest, is strewn.
    for (const bool mirror_y : {false, true}) {
      for (const bool mirror_x : {false, true}) {
        all.push_back({std::string("mirror_add/") + (mirror_y ? "y," : "") + (mirror_x ? "x," : "") + shapes,
                       {in_f("x", logits, 0, 1), inout_f("sum", logits, 0, 3)},
                       [mirror_y, mirror_x](Backend& be, Bound& t) {
                         Ref sum = t.f(1);
                         be.mirror_add(t.f(0), mirror_y, mirror_x, sum);
                       },
                       bits()});
      }
    }
    Arg sums = in_f("values", logits);
    sums.fill = [plane = logits[2] * logits[3]](Rng& rng, void* dst, int64_t n) {
      for (int64_t i = 0; i < n; ++i) {
        float v = static_cast<float>(rng.uniform_int(3));
        if ((i % plane) % 3 == 0) v = -v;
        if (rng.uniform_int(7) == 0) v = std::numeric_limits<float>::quiet_NaN();
        static_cast<float*>(dst)[i] = v;
      }
    };
    all.push_back({"argmax_positive/" + shapes, {sums, out("labels", map, Kind::U8)},
                   [](Backend& be, Bound& t) {
                     LRef labels = t.u8(1);
                     be.argmax_positive(t.f(0), labels);
                   }});
    for (const LossSpec& spec : kLossSpecs) {
      all.push_back({"loss/" + loss_case_name(spec) + shapes,
                     {in_f("logits", logits, -4, 4), labels_arg(map),
                      in_f("coefficients", {13}, 0.5, 4), out("dlogits", logits)},
                     [spec](Backend& be, Bound& t) {
                       Ref dl = t.f(3);
                       t.scalar = be.loss(spec, t.f(0), t.u8(1), t.f(2), dl);
                     },
                     nmse_within(1e-13),
                     true});
    }
  }
  // No labelled cell (every label 0): the loss and its gradient of an empty mean.
  for (const LossSpec& spec : kLossSpecs) {
    Arg unlabelled = labels_arg({1, 4, 5});
    unlabelled.fill = [](Rng&, void* dst, int64_t n) {
      std::memset(dst, 0, static_cast<size_t>(n));
    };
    all.push_back({"loss/" + loss_case_name(spec) + "unlabelled,logits=1x12x4x5",
                   {in_f("logits", {1, 12, 4, 5}, -4, 4), unlabelled,
                    in_f("coefficients", {13}, 0.5, 4), out("dlogits", {1, 12, 4, 5})},
                   [spec](Backend& be, Bound& t) {
                     Ref dl = t.f(3);
                     t.scalar = be.loss(spec, t.f(0), t.u8(1), t.f(2), dl);
                   },
                   bits(),
                   true});
  }
  // An empty batch through the forward ops.
  {
    const Shape x{0, 3, 4, 6};
    all.push_back(
        {"conv2d_forward/empty,x=0x3x4x6,w=5x3x3x3,pad=1",
         {in_f("x", x), in_f("w", {5, 3, 3, 3}), in_f("bias", {5}), out("y", {0, 5, 4, 6})},
         [](Backend& be, Bound& t) {
           Ref bias = t.f(2), y = t.f(3);
           be.conv2d_forward(t.f(0), t.f(1), &bias, 1, y);
         }});
    all.push_back({"maxpool2d_forward/empty,x=0x3x4x6",
                   {in_f("x", x), out("y", {0, 3, 2, 3}), out("argmax", {0, 3, 2, 3}, Kind::I32)},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(1);
                     IRef am = t.i32(2);
                     be.maxpool2d_forward(t.f(0), y, &am);
                   }});
    all.push_back({"upsample_bilinear_forward/empty,x=0x3x4x6",
                   {in_f("x", x), out("y", {0, 3, 8, 12})},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(1);
                     be.upsample_bilinear_forward(t.f(0), y);
                   }});
    all.push_back({"pad_concat_forward/empty,skip=0x3x4x6,up=0x2x3x5",
                   {in_f("skip", x), in_f("up", {0, 2, 3, 5}), out("y", {0, 5, 4, 6})},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(2);
                     be.pad_concat_forward(t.f(0), t.f(1), y);
                   }});
    std::vector<Arg> args = {in_f("x", x)};
    add_bn(args, 3, false, false);
    args.push_back(out("y", x));
    all.push_back({"batchnorm_relu_forward/eval,empty,x=0x3x4x6", args, [](Backend& be, Bound& t) {
                     BatchNormRefs bn = t.bn(1, false);
                     Ref y = t.f(5);
                     be.batchnorm_relu_forward(t.f(0), bn, false, y);
                   }});
    const Shape logits{0, 12, 4, 5};
    all.push_back({"softmax/empty,logits=0x12x4x5",
                   {in_f("logits", logits), out("probs", logits)},
                   [](Backend& be, Bound& t) {
                     Ref probs = t.f(1);
                     be.softmax(t.f(0), probs);
                   }});
    all.push_back({"argmax/empty,logits=0x12x4x5",
                   {in_f("logits", logits), out("labels", {0, 4, 5}, Kind::U8)},
                   [](Backend& be, Bound& t) {
                     LRef labels = t.u8(1);
                     be.argmax(t.f(0), labels);
                   }});
    all.push_back({"loss/ce,empty,logits=0x12x4x5",
                   {in_f("logits", logits), labels_arg({0, 4, 5}),
                    in_f("coefficients", {13}, 0.5, 4), out("dlogits", logits)},
                   [](Backend& be, Bound& t) {
                     Ref dl = t.f(3);
                     t.scalar = be.loss(LossKind::CrossEntropy, t.f(0), t.u8(1), t.f(2), dl);
                   },
                   bits(),
                   true});
  }
  // The optimiser: AdamW with the defaults at step 3, and plain Adam at its first step; the
  // kernel's and the host's FP32 expressions round apart by an ulp or two (of the operands, where
  // m and the parameter cancel to near 0).
  for (const int64_t n : {1, 1000}) {
    for (const bool decay : {true, false}) {
      AdamOptions options;
      if (!decay) options.weight_decay = 0, options.lr = 0.05;
      const int64_t step = decay ? 3 : 1;
      all.push_back(
          {"adam_step/n=" + std::to_string(n) + (decay ? ",adamw,step=3" : ",adam,step=1"),
           {inout_f("param", {n}), in_f("grad", {n}), inout_f("m", {n}, -0.1, 0.1),
            inout_f("v", {n}, 0, 0.1)},
           [options, step](Backend& be, Bound& t) {
             Ref p = t.f(0), m = t.f(2), v = t.f(3);
             be.adam_step(p, t.f(1), m, v, step, options);
           },
           within(1e-8, 1e-6)});
    }
  }
  for (const int64_t n : {0, 1, 1000, 4099}) {
    all.push_back({"sum_of_squares/n=" + std::to_string(n),
                   {in_f("x", {n})},
                   [](Backend& be, Bound& t) { t.scalar = be.sum_of_squares(t.f(0)); },
                   nmse_within(1e-12),
                   true});
    for (const float factor : {0.37f, -2.0f}) {
      all.push_back({"scale/n=" + std::to_string(n) + ",factor=" + std::to_string(factor),
                     {inout_f("x", {n})},
                     [factor](Backend& be, Bound& t) {
                       Ref x = t.f(0);
                       be.scale(x, factor);
                     },
                     bits()});
    }
  }
  for (const int64_t n : {1, 1000}) {
    // Two pieces in flight (the first empty for n = 1), then their end.
    all.push_back({.name = "sum_over_replicas/n=" + std::to_string(n) + ",twin_replicas",
                   .args = {inout_f("values", {n})},
                   .run =
                       [n](Backend& be, Bound& t) {
                         TwinReplicas replicas;
                         Ref first = row_slice("sum_over_replicas", t.f(0), 0, n / 2),
                             second = row_slice("sum_over_replicas", t.f(0), n / 2, n - n / 2);
                         be.begin_sum_over_replicas(first, replicas);
                         be.begin_sum_over_replicas(second, replicas);
                         be.end_sums_over_replicas(replicas);
                       },
                   .tol = bits(),
                   .runs_on =
                       [](const Backend& be, std::string& why) {
#if defined(PILLARSEG_CUDA_EMULATION)
                         static_cast<void>(be);
                         static_cast<void>(why);
                         return true;
#else
                         why =
                             "the CUDA backend on a GPU sums over NCCL between processes "
                             "(tests/mpi)";
                         return be.device() == Device::Cpu;
#endif
                       }});
  }
  add_half_ops(all, Precision::BF16);
  add_half_ops(all, Precision::F16);
  add_int8_ops(all);
  return all;
}

std::vector<std::vector<uint8_t>> host_data(const Case& c, uint64_t seed) {
  Rng rng(seed);
  std::vector<std::vector<uint8_t>> data;
  for (const Arg& a : c.args) {
    std::vector<uint8_t> bytes(a.bytes());
    if (a.role == Role::Output) {
      // NaN floats (0xFFFF is a NaN as BF16 and FP16), -777 and 0xDEADBEEF integers, 0xEE class
      // ids, int8 -128 (which no INT8 weight is): an element no op writes does not compare.
      const auto fill_with = [&bytes](auto junk) {
        for (size_t i = 0; i < bytes.size() / sizeof junk; ++i)
          std::memcpy(bytes.data() + i * sizeof junk, &junk, sizeof junk);
      };
      switch (a.kind) {
        case Kind::F32:
          fill_with(std::numeric_limits<float>::quiet_NaN());
          break;
        case Kind::I32:
          fill_with(int32_t{-777});
          break;
        case Kind::U32:
          fill_with(uint32_t{0xDEADBEEF});
          break;
        case Kind::H16:
          fill_with(uint16_t{0xFFFF});
          break;
        case Kind::U8:
          fill_with(uint8_t{0xEE});
          break;
        case Kind::I8:
          fill_with(int8_t{-128});
          break;
      }
    } else {
      a.fill(rng, bytes.data(), shape_numel(a.shape));
    }
    data.push_back(std::move(bytes));
  }
  return data;
}

// Element i of a tensor's bytes as a double.
double element(const std::vector<uint8_t>& bytes, Kind kind, Precision p, size_t i) {
  switch (kind) {
    case Kind::F32: {
      float v;
      std::memcpy(&v, bytes.data() + 4 * i, 4);
      return v;
    }
    case Kind::H16: {
      uint16_t v;
      std::memcpy(&v, bytes.data() + 2 * i, 2);
      return from_bits(v, p);
    }
    case Kind::I32: {
      int32_t v;
      std::memcpy(&v, bytes.data() + 4 * i, 4);
      return v;
    }
    case Kind::U32: {
      uint32_t v;
      std::memcpy(&v, bytes.data() + 4 * i, 4);
      return v;
    }
    case Kind::U8:
      return bytes[i];
    case Kind::I8:
      return static_cast<int8_t>(bytes[i]);
  }
  return 0;
}

// Elements [0, n) of `got` against `ref` by `tol`: an empty string, or what failed with the
// worst element.
std::string compare(const std::vector<uint8_t>& got, const std::vector<uint8_t>& ref, size_t n,
                    Kind kind, Precision p, Tolerance tol) {
  const bool is_float = kind == Kind::F32 || kind == Kind::H16;
  if (!is_float) tol = bits();
  size_t failures = 0, worst = 0;
  double worst_excess = -1, num = 0, den = 0;
  for (size_t i = 0; i < n; ++i) {
    const double a = element(got, kind, p, i), r = element(ref, kind, p, i);
    const size_t width = kind_bytes(kind);
    bool ok;
    double excess = 0;
    if (std::isnan(a) || std::isnan(r) || std::isinf(a) || std::isinf(r)) {
      ok = (std::isnan(a) && std::isnan(r)) || a == r;  // NaN and Inf must match
      excess = ok ? 0 : std::numeric_limits<double>::infinity();
    } else if (tol.mode == Tolerance::Mode::Bits) {
      ok = std::memcmp(got.data() + i * width, ref.data() + i * width, width) == 0;
      excess = std::abs(a - r);
    } else {
      const double bound = tol.atol + tol.rtol * std::abs(r);
      excess = std::abs(a - r) - bound;
      ok = tol.mode == Tolerance::Mode::Nmse || excess <= 0;
      num += (a - r) * (a - r);
      den += r * r;
    }
    if (!ok) ++failures;
    if ((!ok || tol.mode == Tolerance::Mode::Nmse) && excess > worst_excess)
      worst_excess = excess, worst = i;
  }
  std::ostringstream message;
  if (tol.mode == Tolerance::Mode::Nmse && failures == 0) {
    const double e = den > 0 ? num / den : num;
    if (e <= tol.max_nmse) return "";
    message << "NMSE " << e << " > " << tol.max_nmse;
  } else if (failures == 0) {
    return "";
  } else {
    const char* how = tol.mode == Tolerance::Mode::Bits   ? " in their bits"
                      : tol.mode == Tolerance::Mode::Nmse ? " in NaN or Inf"
                                                          : " beyond atol + rtol |ref|";
    message << failures << " of " << n << " elements differ" << how;
  }
  message.precision(9);
  message << "; worst element " << worst << ": " << element(got, kind, p, worst) << " vs "
          << element(ref, kind, p, worst) << " (the reference)";
  return message.str();
}

bool backend_runs(const Backend& be, const Case& c, std::string& why) {
  if (c.runs_on && !c.runs_on(be, why)) return false;
  if (c.precision == Precision::F32) return true;
  return c.training ? be.supports_training_precision(c.precision, &why)
                    : be.supports_precision(c.precision, &why);
}

// The CPU backend; for a BF16 case where this CPU lacks AVX512_BF16, or an INT8 case where it
// lacks AVX512-VNNI, the same kernels on the model of its instructions.
std::unique_ptr<Backend> cpu_backend_for(const Case& c) {
  auto be = make_cpu_backend();
  if ((c.precision == Precision::BF16 || c.precision == Precision::I8) &&
      !be->supports_precision(c.precision))
    return make_cpu_backend_emulated_bf16();
  return be;
}

struct BackendUnderTest {
  const char* name;
  std::function<std::unique_ptr<Backend>(const Case&)> make;
};

std::vector<BackendUnderTest> backends() {
  std::vector<BackendUnderTest> list = {{"cpu", cpu_backend_for}};
#ifdef PILLARSEG_CUDA_EMULATION
  list.push_back({"emu", [](const Case&) { return std::unique_ptr<Backend>(new CudaBackend()); }});
#else
  list.push_back({"cuda", [](const Case&) { return std::unique_ptr<Backend>(new CudaBackend()); }});
#endif
  return list;
}

const std::vector<Case>& table() {
  static const std::vector<Case> all = cases();
  return all;
}

class BackendOps : public ::testing::TestWithParam<size_t> {};

TEST_P(BackendOps, MatchesTheReference) {
  const Case& c = table()[GetParam()];
  const std::vector<std::vector<uint8_t>> data = host_data(c, 1000 + GetParam());
  auto reference = make_cpu_reference_backend();
  Bound ref(*reference, c.args, data);
  if (c.reference)
    c.reference(ref);
  else
    c.run(*reference, ref);
  int ran = 0;
  for (const BackendUnderTest& b : backends()) {
    SCOPED_TRACE(std::string(b.name) + " " + c.name);
    auto backend = b.make(c);
    std::string why;
    if (!backend_runs(*backend, c, why)) {
      RecordProperty(std::string("not_on_") + b.name, why);
      continue;
    }
    ++ran;
    Bound got(*backend, c.args, data);
    c.run(*backend, got);
    const Tolerance case_tol = backend->device() == Device::Cpu && c.cpu_tol ? *c.cpu_tol : c.tol;
    for (size_t i = 0; i < c.args.size(); ++i) {
      const Arg& a = c.args[i];
      bool guards_ref = false, guards_got = false;
      const std::vector<uint8_t> r = ref.download(i, guards_ref);
      const std::vector<uint8_t> g = got.download(i, guards_got);
      EXPECT_TRUE(guards_ref) << "the reference wrote outside " << a.name;
      EXPECT_TRUE(guards_got) << b.name << " wrote outside " << a.name;
      if (a.role == Role::Input) {
        EXPECT_EQ(g, data[i]) << b.name << " changed its input " << a.name;
        continue;
      }
      const size_t n = static_cast<size_t>(shape_numel(a.shape));
      size_t compared = n;
      if (a.live_rows_from >= 0) {
        // The leading P' rows; the rest inert where the backend said it wrote them.
        bool intact = false;
        const std::vector<uint8_t> live =
            ref.download(static_cast<size_t>(a.live_rows_from), intact);
        const size_t rows = static_cast<size_t>(a.shape.at(0)), row = rows > 0 ? n / rows : 0;
        const size_t kept = std::min(
            rows, static_cast<size_t>(std::max(0.0, element(live, Kind::I32, c.precision, 0))));
        compared = kept * row;
        const size_t written = got.rows < 0 ? kept : std::min(rows, static_cast<size_t>(got.rows));
        for (size_t e = compared; a.inert && e < written * row; ++e)
          ASSERT_EQ(element(g, a.kind, c.precision, e), *a.inert)
              << b.name << " " << a.name << "[" << e / row << "]: a row past P' = " << kept
              << " is not inert";
      }
      const std::string failed =
          compare(g, r, compared, a.kind, c.precision, a.tol ? *a.tol : case_tol);
      EXPECT_EQ(failed, "") << b.name << " " << a.name;
    }
    if (c.compare_scalar) {
      // The returned value (a loss, a sum): equal, or its squared error relative to the
      // reference's square within the NMSE bound, or per element's bound.
      const double d = got.scalar - ref.scalar, r = ref.scalar;
      const bool close = case_tol.mode == Tolerance::Mode::Bits ? got.scalar == r
                         : case_tol.mode == Tolerance::Mode::Nmse
                             ? d * d <= case_tol.max_nmse * r * r
                             : std::abs(d) <= case_tol.atol + case_tol.rtol * std::abs(r);
      EXPECT_TRUE(close) << b.name << ": returned " << got.scalar << ", the reference " << r;
    }
  }
  EXPECT_GT(ran, 0) << "no backend of this build runs " << c.name;
}

std::string case_name(const ::testing::TestParamInfo<size_t>& info) {
  std::string s = table()[info.param].name;
  for (char& ch : s)
    if (!std::isalnum(static_cast<unsigned char>(ch))) ch = '_';
  return s;
}

// The harness itself: a byte written just past a tensor breaks its guard, an output left
// unwritten (still NaN) compares as infinitely wrong, and the comparison names the worst element.
TEST(BackendOpsHarness, GuardsAndUnwrittenOutputsFail) {
  const std::vector<Arg> args = {out("y", {3, 4})};
  Case c{"probe", args, {}};
  const std::vector<std::vector<uint8_t>> data = host_data(c, 1);
  auto be = make_cpu_backend();
  Bound t(*be, args, data);
  bool intact = false;
  const std::vector<uint8_t> written(12 * 4, 0);  // twelve zeros, as a reference would hold
  EXPECT_NE(compare(t.download(0, intact), written, 12, Kind::F32, Precision::F32, nmse_within(1)),
            "");
  EXPECT_TRUE(intact);
  reinterpret_cast<uint8_t*>(t.f(0).data)[12 * 4] = 0;  // one byte past the end
  t.download(0, intact);
  EXPECT_FALSE(intact);
}

TEST(BackendOpsHarness, ComparisonsNameTheWorstElement) {
  const auto floats = [](std::vector<float> v) {
    std::vector<uint8_t> b(v.size() * 4);
    std::memcpy(b.data(), v.data(), b.size());
    return b;
  };
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const std::vector<uint8_t> ref = floats({1.0f, 2.0f, nan, 4.0f});
  EXPECT_EQ(compare(ref, ref, 4, Kind::F32, Precision::F32, bits()), "");  // NaN matches NaN
  const std::string one_bit = compare(floats({1.0f, std::nextafter(2.0f, 3.0f), nan, 4.0f}), ref, 4,
                                      Kind::F32, Precision::F32, bits());
  EXPECT_NE(one_bit.find("1 of 4 elements differ in their bits; worst element 1"),
            std::string::npos)
      << one_bit;
  // |a - r| <= 0.01 + 0.1 |r|: 4.3 is within 0.41 of 4, 2.5 is not within 0.21 of 2.
  const std::vector<uint8_t> got = floats({1.0f, 2.5f, nan, 4.3f});
  const std::string far = compare(got, ref, 4, Kind::F32, Precision::F32, within(0.01, 0.1));
  EXPECT_NE(far.find("1 of 4 elements differ beyond atol + rtol |ref|; worst element 1: 2.5 vs 2"),
            std::string::npos)
      << far;
  EXPECT_NE(
      compare(floats({1.0f, 2.0f, 3.0f, 4.0f}), ref, 4, Kind::F32, Precision::F32, within(1, 1)),
      "")
      << "a number where the reference has NaN";
  EXPECT_EQ(compare(got, ref, 2, Kind::F32, Precision::F32, within(0, 0.25)),
            "");  // the first two only
  // NMSE: (0.5^2 + 0.3^2) / (1 + 4 + 16) = 0.01619.
  const std::string nmse_failure =
      compare(got, ref, 4, Kind::F32, Precision::F32, nmse_within(0.016));
  EXPECT_NE(nmse_failure.find("NMSE 0.0161"), std::string::npos) << nmse_failure;
  EXPECT_EQ(compare(got, ref, 4, Kind::F32, Precision::F32, nmse_within(0.0162)), "");
}

INSTANTIATE_TEST_SUITE_P(Table, BackendOps, ::testing::Range<size_t>(0, table().size()), case_name);

}  // namespace
