// Every op of the Backend interface on every backend of this build against the CPU reference
// backend (host/ ops alone), from one table of cases, in the manner of ggml's test-backend-ops:
//   - the backends under test: the CPU backend (its Winograd and fused paths), and the CUDA
//     backend, on the emulation in test_backend_ops and on the GPU in test_backend_ops_gpu;
//   - each case names the op and its shapes ("conv2d_forward/x=2x3x7x5,w=4x3x3x3,pad=1"), and
//     gives its tensors (inputs, outputs, and in-outs such as a canvas that an op writes a band
//     of, or running statistics) with their random contents;
//   - every tensor lies between guard words: an op that writes a byte outside its tensor fails,
//     and outputs start as NaN (integers as -777) so that an element left unwritten fails too;
//   - float results are compared by normalised mean squared error, NMSE = sum (a - r)^2 /
//     sum r^2, against a per-case bound; integer results and class maps exactly.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <memory>
#include <numeric>
#include <string>
#include <vector>

#include "core/rng.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/model/backend.hpp"

using namespace pillarseg;

namespace {

enum class Kind { F32, I32, U8 };
enum class Role { Input, Output, InOut };

constexpr size_t kGuardBytes = 64;
constexpr uint8_t kGuardByte = 0xA5;

size_t kind_bytes(Kind k) {
  return k == Kind::U8 ? 1 : 4;
}

std::string shape_name(const Shape& s) {
  std::string out;
  for (size_t i = 0; i < s.size(); ++i) {
    if (i > 0) out.push_back('x');
    out.append(std::to_string(s[i]));
  }
  return out;
}

struct Arg {
  std::string name;
  Shape shape;
  Kind kind = Kind::F32;
  Role role = Role::Input;
  // Fills the host bytes of an input or in-out (numel elements of `kind`).
  std::function<void(Rng&, void*, int64_t)> fill;
  size_t bytes() const { return static_cast<size_t>(shape_numel(shape)) * kind_bytes(kind); }
};

// The case's tensors in one backend's memory, each between two guard regions.
class Bound {
 public:
  Bound(Backend& be, const std::vector<Arg>& args, const std::vector<std::vector<uint8_t>>& host)
      : be_(be) {
    for (size_t i = 0; i < args.size(); ++i) {
      const size_t total = args[i].bytes() + 2 * kGuardBytes;
      std::vector<uint8_t> image(total, kGuardByte);
      std::memcpy(image.data() + kGuardBytes, host[i].data(), args[i].bytes());
      uint8_t* block = static_cast<uint8_t*>(be.allocate(total));
      be.upload(block, image.data(), total);
      blocks_.push_back(block);
      sizes_.push_back(total);
    }
    args_ = &args;
  }
  ~Bound() {
    for (uint8_t* b : blocks_) be_.deallocate(b);
  }
  Bound(const Bound&) = delete;
  Bound& operator=(const Bound&) = delete;

  Ref f(size_t i) {
    return {reinterpret_cast<float*>(blocks_[i] + kGuardBytes), (*args_)[i].shape};
  }
  IRef i32(size_t i) {
    return {reinterpret_cast<int32_t*>(blocks_[i] + kGuardBytes), (*args_)[i].shape};
  }
  LRef u8(size_t i) { return {blocks_[i] + kGuardBytes, (*args_)[i].shape}; }
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
  double scalar = 0;  // an op's returned value (the loss)

 private:
  Backend& be_;
  const std::vector<Arg>* args_ = nullptr;
  std::vector<uint8_t*> blocks_;
  std::vector<size_t> sizes_;
};

struct Case {
  std::string name;
  std::vector<Arg> args;
  std::function<void(Backend&, Bound&)> run;
  double max_nmse = 1e-10;
  bool compare_scalar = false;
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
// Cells (P, 3) of P distinct (sample, iy, ix) of a (B, H, W) grid.
Arg cells_arg(int64_t p, int64_t b, int64_t h, int64_t w) {
  Arg a{"cells", {p, 3}, Kind::I32, Role::Input, {}};
  a.fill = [b, h, w](Rng& rng, void* dst, int64_t n) {
    std::vector<int64_t> all(static_cast<size_t>(b * h * w));
    std::iota(all.begin(), all.end(), 0);
    rng.shuffle(all.begin(), all.end());
    int32_t* c = static_cast<int32_t*>(dst);
    for (int64_t r = 0; r < n / 3; ++r) {
      const int64_t k = all[static_cast<size_t>(r)];
      c[3 * r] = static_cast<int32_t>(k / (h * w));
      c[3 * r + 1] = static_cast<int32_t>(k / w % h);
      c[3 * r + 2] = static_cast<int32_t>(k % w);
    }
  };
  return a;
}
Arg labels_arg(Shape shape) {
  Arg a{"labels", std::move(shape), Kind::U8, Role::Input, {}};
  a.fill = [](Rng& rng, void* dst, int64_t n) {
    uint8_t* l = static_cast<uint8_t*>(dst);
    for (int64_t i = 0; i < n; ++i)
      l[i] = static_cast<uint8_t>(rng.uniform_int(13));  // 0 = unlabelled
  };
  return a;
}

// ---- the table ----

std::vector<Case> cases() {
  std::vector<Case> all;
  // Convolutions: 3x3 pad 1, 1x1 (the head), odd sizes, and channel counts that are not a
  // multiple of a tile.
  for (const auto& [x, w, pad] :
       std::vector<std::tuple<Shape, Shape, int>>{{{2, 3, 7, 5}, {4, 3, 3, 3}, 1},
                                                  {{1, 8, 6, 6}, {5, 8, 3, 3}, 1},
                                                  {{2, 6, 5, 4}, {12, 6, 1, 1}, 0},
                                                  {{1, 17, 9, 11}, {33, 17, 3, 3}, 1},
                                                  {{1, 2, 5, 5}, {3, 2, 3, 3}, 0}}) {
    const std::string shapes =
        "x=" + shape_name(x) + ",w=" + shape_name(w) + ",pad=" + std::to_string(pad);
    const Shape y{x[0], w[0], x[2] + 2 * pad - w[2] + 1, x[3] + 2 * pad - w[3] + 1};
    all.push_back({"conv2d_forward/" + shapes,
                   {in_f("x", x), in_f("w", w), in_f("bias", {w[0]}), out("y", y)},
                   [pad](Backend& be, Bound& t) {
                     Ref bias = t.f(2), yy = t.f(3);
                     be.conv2d_forward(t.f(0), t.f(1), &bias, pad, yy);
                   },
                   1e-9});
    all.push_back({"conv2d_backward/" + shapes,
                   {in_f("x", x), in_f("w", w), in_f("dy", y), out("dx", x), out("dw", w),
                    out("dbias", {w[0]})},
                   [pad](Backend& be, Bound& t) {
                     Ref dx = t.f(3), dw = t.f(4), db = t.f(5);
                     be.conv2d_backward(t.f(0), t.f(1), t.f(2), pad, &dx, dw, &db);
                   },
                   1e-9});
    std::vector<Arg> args = {in_f("x", x), in_f("w", w), in_f("bias", {w[0]})};
    add_bn(args, w[0], false, false);
    args.push_back(out("y", y));
    all.push_back({"conv2d_bn_relu_eval/" + shapes, args,
                   [pad](Backend& be, Bound& t) {
                     Ref bias = t.f(2), yy = t.f(7);
                     be.conv2d_bn_relu_eval(t.f(0), t.f(1), &bias, t.bn(3, false), pad, yy);
                   },
                   1e-9});
  }
  for (const auto& [x, o] :
       std::vector<std::pair<Shape, int64_t>>{{{2, 6, 3, 4}, 3}, {{1, 16, 5, 7}, 8}}) {
    const std::string shapes = "x=" + shape_name(x) + ",o=" + std::to_string(o);
    const Shape w{x[1], o, 2, 2}, y{x[0], o, 2 * x[2], 2 * x[3]};
    all.push_back({"conv_transpose2d_forward/" + shapes,
                   {in_f("x", x), in_f("w", w), in_f("bias", {o}), out("y", y)},
                   [](Backend& be, Bound& t) {
                     Ref bias = t.f(2), yy = t.f(3);
                     be.conv_transpose2d_forward(t.f(0), t.f(1), &bias, yy);
                   }});
    // dy is an input: no backend may change it.
    all.push_back({"conv_transpose2d_backward/" + shapes,
                   {in_f("x", x), in_f("w", w), in_f("dy", y), out("dx", x), out("dw", w), out("dbias", {o})},
                   [](Backend& be, Bound& t) {
                     Ref dx = t.f(3), dw = t.f(4), db = t.f(5);
                     be.conv_transpose2d_backward(t.f(0), t.f(1), t.f(2), dx, dw, &db);
                   },
                   1e-10});
  }
  // BatchNorm + ReLU.
  for (const Shape& x : std::vector<Shape>{{2, 3, 5, 4}, {1, 7, 9, 3}}) {
    const std::string shapes = "x=" + shape_name(x);
    for (bool training : {false, true}) {
      std::vector<Arg> args = {in_f("x", x)};
      add_bn(args, x[1], training, training);
      args.push_back(out("y", x));
      const size_t y = args.size() - 1;
      all.push_back(
          {std::string("batchnorm_relu_forward/") + (training ? "train," : "eval,") + shapes, args,
           [training, y](Backend& be, Bound& t) {
             BatchNormRefs bn = t.bn(1, training);
             Ref yy = t.f(y);
             be.batchnorm_relu_forward(t.f(0), bn, training, yy);
           }});
    }
    std::vector<Arg> args = {in_f("x", x), in_f("y", x, 0, 1), in_f("dy", x)};
    add_bn(args, x[1], false, false, /*saved_in=*/true);
    args.push_back(out("dx", x));
    args.push_back(out("dgamma", {x[1]}));
    args.push_back(out("dbeta", {x[1]}));
    all.push_back({"batchnorm_relu_backward/" + shapes, args, [](Backend& be, Bound& t) {
                     Ref dx = t.f(9), dg = t.f(10), db = t.f(11);
                     be.batchnorm_relu_backward(t.f(0), t.f(1), t.f(2), t.bn(3, true), dx, dg, db);
                   }});
  }
  // Pooling, upsampling, joins, channel copies.
  for (const Shape& x : std::vector<Shape>{{2, 3, 6, 8}, {1, 4, 7, 5}}) {
    const Shape p{x[0], x[1], x[2] / 2, x[3] / 2};
    all.push_back({"maxpool2x2_forward/x=" + shape_name(x),
                   {in_f("x", x), out("y", p), out("argmax", p, Kind::I32)},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(1);
                     IRef am = t.i32(2);
                     be.maxpool2x2_forward(t.f(0), y, am);
                   }});
    all.push_back(
        {"maxpool2x2_backward/x=" + shape_name(x),
         {in_f("x", x), in_f("dy", p), out("dx", x), out("y", p), out("argmax", p, Kind::I32)},
         [](Backend& be, Bound& t) {
           Ref y = t.f(3), dx = t.f(2);
           IRef am = t.i32(4);
           be.maxpool2x2_forward(t.f(0), y, am);
           be.maxpool2x2_backward(t.f(1), am, dx);
         }});
    const Shape u{x[0], x[1], 2 * x[2], 2 * x[3]};
    all.push_back({"upsample2x_forward/x=" + shape_name(x),
                   {in_f("x", x), out("y", u)},
                   [](Backend& be, Bound& t) {
                     Ref y = t.f(1);
                     be.upsample2x_forward(t.f(0), y);
                   }});
    all.push_back({"upsample2x_backward/x=" + shape_name(x),
                   {in_f("dy", u), out("dx", x)},
                   [](Backend& be, Bound& t) {
                     Ref dx = t.f(1);
                     be.upsample2x_backward(t.f(0), dx);
                   }});
  }
  for (const auto& [skip, up] : std::vector<std::pair<Shape, Shape>>{
           {{2, 3, 6, 8}, {2, 4, 6, 8}}, {{1, 2, 7, 9}, {1, 3, 6, 8}}}) {
    const Shape y{skip[0], skip[1] + up[1], skip[2], skip[3]};
    const std::string shapes = "skip=" + shape_name(skip) + ",up=" + shape_name(up);
    all.push_back({"pad_concat_forward/" + shapes,
                   {in_f("skip", skip), in_f("up", up), out("y", y)},
                   [](Backend& be, Bound& t) {
                     Ref yy = t.f(2);
                     be.pad_concat_forward(t.f(0), t.f(1), yy);
                   }});
    all.push_back({"pad_concat_backward/" + shapes,
                   {in_f("dy", y), out("dskip", skip), out("dup", up)},
                   [](Backend& be, Bound& t) {
                     Ref ds = t.f(1), du = t.f(2);
                     be.pad_concat_backward(t.f(0), ds, du);
                   }});
  }
  {
    const Shape x{2, 3, 4, 5}, y{2, 8, 4, 5};
    all.push_back({"copy_channels/x=2x3x4x5,y=2x8x4x5,c0=4",
                   {in_f("x", x), inout_f("y", y)},
                   [](Backend& be, Bound& t) {
                     Ref yy = t.f(1);
                     be.copy_channels(t.f(0), 4, yy);
                   }});
    all.push_back({"extract_channels/x=2x3x4x5,y=2x8x4x5,c0=2",
                   {in_f("y", y), out("x", x)},
                   [](Backend& be, Bound& t) {
                     Ref xx = t.f(1);
                     be.extract_channels(t.f(0), 2, xx);
                   }});
    all.push_back(
        {"add_inplace/a=2x3x4x5", {inout_f("a", x), in_f("b", x)}, [](Backend& be, Bound& t) {
           Ref a = t.f(0);
           be.add_inplace(a, t.f(1));
         }});
  }
  // Pillars: PFN forward (eval, training) and backward, scatter and its backward; 70 pillars of
  // 20 points are three of the CPU backend's blocks of 32, the last one short.
  for (const auto& [p, n, c] :
       std::vector<std::tuple<int64_t, int64_t, int64_t>>{{5, 3, 4}, {37, 8, 16}, {70, 20, 64}}) {
    const std::string shapes = "points=" + shape_name({p, n, 10}) + ",c=" + std::to_string(c);
    for (bool training : {false, true}) {
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
                     1e-9});
    }
    // Evaluation with live rows (a device pipeline's P'): the rows from p / 2 on keep their
    // random contents (the reference leaves them too), the others are computed; a live count
    // past the rows (p + 5) computes every row.
    for (const int64_t live : {p / 2, p + 5}) {
      std::vector<Arg> eval_args = {in_f("points", {p, n, 10}), in_f("weight", {c, 10})};
      add_bn(eval_args, c, false, false);
      eval_args.push_back(inout_f("out", {p, c}, -9, -8));
      Arg live_arg{"live_rows", {1}, Kind::I32, Role::Input, {}};
      live_arg.fill = [live](Rng&, void* dst, int64_t) {
        *static_cast<int32_t*>(dst) = static_cast<int32_t>(live);
      };
      eval_args.push_back(live_arg);
      all.push_back({"pfn_forward/eval,live=" + std::to_string(live) + "," + shapes, eval_args,
                     [](Backend& be, Bound& t) {
                       BatchNormRefs bn = t.bn(2, false);
                       Ref y = t.f(6);
                       IRef am;
                       be.pfn_forward(t.f(0), t.f(1), bn, false, t.i32(7), am, y);
                     },
                     1e-9});
    }
    // The backward after a training forward on the same backend (its arg-max slots).
    std::vector<Arg> args = {in_f("points", {p, n, 10}), in_f("weight", {c, 10})};
    add_bn(args, c, true, true);
    for (Arg a : {out("out", {p, c}), out("argmax", {p, c}, Kind::I32)}) args.push_back(a);
    for (Arg a : {in_f("dout", {p, c}), out("dweight", {c, 10}), out("dgamma", {c}), out("dbeta", {c})})
      args.push_back(a);
    all.push_back({"pfn_backward/" + shapes, args,
                   [](Backend& be, Bound& t) {
                     BatchNormRefs bn = t.bn(2, true);
                     Ref y = t.f(8), dw = t.f(11), dg = t.f(12), db = t.f(13);
                     IRef am = t.i32(9);
                     be.pfn_forward(t.f(0), t.f(1), bn, true, IRef{}, am, y);
                     be.pfn_backward(t.f(0), t.f(1), bn, am, t.f(10), dw, dg, db);
                   },
                   1e-9});
    const int64_t b = 2, h = 6, w = 7, cc = c + 3;
    all.push_back(
        {"scatter_forward/" + shapes,
         {in_f("features", {p, c}), cells_arg(p, b, h, w), inout_f("canvas", {b, cc, h, w})},
         [](Backend& be, Bound& t) {
           Ref canvas = t.f(2);
           be.scatter_forward(t.f(0), t.i32(1), 2, canvas);
         }});
    all.push_back(
        {"scatter_backward/" + shapes,
         {in_f("dcanvas", {b, cc, h, w}), cells_arg(p, b, h, w), out("dfeatures", {p, c})},
         [](Backend& be, Bound& t) {
           Ref df = t.f(2);
           be.scatter_backward(t.f(0), t.i32(1), 1, df);
         }});
  }
  // The head: softmax, class map, both losses.
  for (const Shape& logits : std::vector<Shape>{{1, 12, 4, 5}, {2, 12, 7, 3}}) {
    const std::string shapes = "logits=" + shape_name(logits);
    const Shape map{logits[0], logits[2], logits[3]};
    all.push_back({"softmax/" + shapes,
                   {in_f("logits", logits, -4, 4), out("probs", logits)},
                   [](Backend& be, Bound& t) {
                     Ref probs = t.f(1);
                     be.softmax(t.f(0), probs);
                   }});
    all.push_back({"argmax/" + shapes,
                   {in_f("logits", logits, -4, 4), out("labels", map, Kind::U8)},
                   [](Backend& be, Bound& t) {
                     LRef labels = t.u8(1);
                     be.argmax(t.f(0), labels);
                   }});
    for (LossKind kind : {LossKind::CrossEntropy, LossKind::Bce}) {
      all.push_back({std::string("loss/") + (kind == LossKind::Bce ? "bce," : "ce,") + shapes,
                     {in_f("logits", logits, -4, 4), labels_arg(map),
                      in_f("coefficients", {13}, 0.5, 4), out("dlogits", logits)},
                     [kind](Backend& be, Bound& t) {
                       Ref dl = t.f(3);
                       t.scalar = be.loss(kind, t.f(0), t.u8(1), t.f(2), dl);
                     },
                     1e-10,
                     true});
    }
  }
  // The optimiser.
  all.push_back({"adam_step/n=1000",
                 {inout_f("param", {1000}), in_f("grad", {1000}), inout_f("m", {1000}, -0.1, 0.1),
                  inout_f("v", {1000}, 0, 0.1)},
                 [](Backend& be, Bound& t) {
                   Ref p = t.f(0), m = t.f(2), v = t.f(3);
                   be.adam_step(p, t.f(1), m, v, 3, AdamOptions{});
                 }});
  all.push_back({"sum_of_squares/n=1000",
                 {in_f("x", {1000})},
                 [](Backend& be, Bound& t) { t.scalar = be.sum_of_squares(t.f(0)); },
                 1e-10,
                 true});
  return all;
}

std::vector<std::vector<uint8_t>> host_data(const Case& c, uint64_t seed) {
  Rng rng(seed);
  std::vector<std::vector<uint8_t>> data;
  for (const Arg& a : c.args) {
    std::vector<uint8_t> bytes(a.bytes());
    if (a.role == Role::Output) {
      // NaN floats, -777 integers, 0xEE class ids: an element no op writes does not compare.
      if (a.kind == Kind::F32) {
        const float nan = std::numeric_limits<float>::quiet_NaN();
        for (size_t i = 0; i < bytes.size() / 4; ++i) std::memcpy(bytes.data() + 4 * i, &nan, 4);
      } else if (a.kind == Kind::I32) {
        const int32_t junk = -777;
        for (size_t i = 0; i < bytes.size() / 4; ++i) std::memcpy(bytes.data() + 4 * i, &junk, 4);
      } else {
        std::fill(bytes.begin(), bytes.end(), uint8_t{0xEE});
      }
    } else {
      a.fill(rng, bytes.data(), shape_numel(a.shape));
    }
    data.push_back(std::move(bytes));
  }
  return data;
}

double nmse(const std::vector<uint8_t>& a, const std::vector<uint8_t>& r) {
  const size_t n = a.size() / 4;
  const float* x = reinterpret_cast<const float*>(a.data());
  const float* y = reinterpret_cast<const float*>(r.data());
  double num = 0, den = 0;
  for (size_t i = 0; i < n; ++i) {
    const double d = static_cast<double>(x[i]) - y[i];
    num += d * d;
    den += static_cast<double>(y[i]) * y[i];
  }
  if (!std::isfinite(num)) return std::numeric_limits<double>::infinity();
  return den > 0 ? num / den : num;
}

struct BackendUnderTest {
  const char* name;
  std::function<std::unique_ptr<Backend>()> make;
};

std::vector<BackendUnderTest> backends() {
  std::vector<BackendUnderTest> list = {{"cpu", [] { return make_cpu_backend(); }}};
#ifdef PILLARSEG_CUDA_EMULATION
  list.push_back({"emu", [] { return std::unique_ptr<Backend>(new CudaBackend()); }});
#else
  list.push_back({"cuda", [] { return std::unique_ptr<Backend>(new CudaBackend()); }});
#endif
  return list;
}

class BackendOps : public ::testing::TestWithParam<size_t> {};

TEST_P(BackendOps, MatchesTheReference) {
  static const std::vector<Case> table = cases();
  const Case& c = table[GetParam()];
  const std::vector<std::vector<uint8_t>> data = host_data(c, 1000 + GetParam());
  auto reference = make_cpu_reference_backend();
  Bound ref(*reference, c.args, data);
  c.run(*reference, ref);
  for (const BackendUnderTest& b : backends()) {
    SCOPED_TRACE(std::string(b.name) + " " + c.name);
    auto backend = b.make();
    Bound got(*backend, c.args, data);
    c.run(*backend, got);
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
      if (a.kind == Kind::F32) {
        const double e = nmse(g, r);
        EXPECT_LE(e, c.max_nmse) << b.name << " " << a.name << ": NMSE " << e;
      } else {
        EXPECT_EQ(g, r) << b.name << " " << a.name;
      }
    }
    if (c.compare_scalar) {
      const double d = got.scalar - ref.scalar;
      EXPECT_LE(d * d, c.max_nmse * ref.scalar * ref.scalar)
          << b.name << ": " << got.scalar << " vs " << ref.scalar;
    }
  }
}

std::string case_name(const ::testing::TestParamInfo<size_t>& info) {
  static const std::vector<Case> table = cases();
  std::string s = table[info.param].name;
  for (char& ch : s)
    if (!std::isalnum(static_cast<unsigned char>(ch))) ch = '_';
  return s;
}

// The harness itself: a byte written just past a tensor breaks its guard, and an output left
// unwritten (still NaN) compares as infinitely wrong.
TEST(BackendOpsHarness, GuardsAndUnwrittenOutputsFail) {
  const std::vector<Arg> args = {out("y", {3, 4})};
  Case c{"probe", args, {}};
  const std::vector<std::vector<uint8_t>> data = host_data(c, 1);
  auto be = make_cpu_backend();
  Bound t(*be, args, data);
  bool intact = false;
  EXPECT_EQ(nmse(t.download(0, intact), data[0]), std::numeric_limits<double>::infinity());
  EXPECT_TRUE(intact);
  reinterpret_cast<uint8_t*>(t.f(0).data)[12 * 4] = 0;  // one byte past the end
  t.download(0, intact);
  EXPECT_FALSE(intact);
}

INSTANTIATE_TEST_SUITE_P(Table, BackendOps, ::testing::Range<size_t>(0, cases().size()), case_name);

}  // namespace
