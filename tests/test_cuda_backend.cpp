// CudaBackend (engine/cuda/) on the CUDA emulation against CpuBackend, whole PillarSegNet at a
// tiny size (24 x 16 grid, base width 4, depth 2): forward logits, both losses, every parameter
// gradient, running statistics, an AdamW step, evaluation logits and class maps, for the
// bilinear and transposed U-Nets with the pillar and occupancy streams. Then what only the CUDA
// backend has: the evaluation forward replayed as a graph matches the uncaptured forward bit for
// bit (across pillar counts, parameter updates and re-plans), the steady-state training loop
// allocates nothing, uploads larger than the staging buffer arrive whole, and the errors say what
// is wrong. Last, the convolution choice (--conv): in the GPU build (test_cuda_backend_gpu) the
// cuDNN and cuBLAS paths against our kernels, pass by pass at the U-Net's kinds of layers and as
// the whole tiny model (training and the graph-replayed evaluation); in the emulated build, that
// asking for them throws.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "core/replicas.hpp"
#include "core/rng.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "tests/support/test_support.hpp"
#include "tests/support/tiny_model.hpp"

using namespace pillarseg;
using pillarseg::test::kCoefficients;
using pillarseg::test::tiny_config;
using pillarseg::test::tiny_data;
using pillarseg::test::TinyData;

namespace {

Tensor<float> as_tensor(const std::vector<float>& v) {
  Tensor<float> t({static_cast<int64_t>(v.size())});
  std::copy(v.begin(), v.end(), t.begin());
  return t;
}

// The largest |x|: gradients of different layers differ by orders of magnitude, so their
// tolerance is relative to the tensor's own scale.
double max_abs(const Tensor<float>& t) {
  double m = 0;
  for (float v : t) m = std::max(m, static_cast<double>(std::abs(v)));
  return m;
}

// One AdamW step over all trainable parameters.
void adam(Backend& backend, ParameterSet& ps, int64_t step) {
  AdamOptions adam;
  adam.lr = 1e-2;
  adam.beta2 = 0.99;
  Ref values = ps.values(), m = ps.adam_m(), v = ps.adam_v();
  backend.adam_step(values, ps.grads(), m, v, step, adam);
}

struct Variant {
  const char* name;
  OccupancyInput occupancy;
  bool transposed, grid_map;
};

const Variant kVariants[] = {
    {"bilinear_occupancy2d", OccupancyInput::Observability2D, false, false},
    {"transposed_occupancy2d", OccupancyInput::Observability2D, true, false},
    {"bilinear_occupancy3d_gridmap", OccupancyInput::Occupancy3D, false, true},
};

// Per-quantity tolerances, |cuda - cpu| <= atol + rtol |cpu|. The two backends sum in different
// orders (tiled GEMMs, per-block partial sums in double) over at most a few hundred terms per
// output, in float; training-mode BatchNorm divides by a batch deviation and so amplifies the
// differences through the depth, which the gradients inherit. Measured worst cases over the
// variants below: logits 2.4e-6 relative, losses 1e-8 relative, gradients 1.5e-7 absolute
// (3.5e-5 relative); the tolerances leave a margin of about 5 to 10.
constexpr double kForwardRtol = 2e-5, kForwardAtol = 2e-6;
constexpr double kLossRtol = 1e-6;
constexpr double kGradientRtol = 2e-4, kGradientAtolScale = 2e-5, kGradientAtolFloor = 1e-7;

}  // namespace

class CudaBackendModel : public ::testing::TestWithParam<Variant> {};

TEST_P(CudaBackendModel, MatchesTheCpuBackend) {
  const Variant& variant = GetParam();
  const ModelConfig c = tiny_config(variant.occupancy, variant.transposed, variant.grid_map);
  auto cpu = make_cpu_reference_backend();
  CudaBackend cuda;
  PillarSegNet cpu_net(c, *cpu, /*seed=*/7), cuda_net(c, cuda, /*seed=*/7);
  ParameterSet &cpu_ps = cpu_net.parameters(), &cuda_ps = cuda_net.parameters();
  ASSERT_EQ(cuda_ps.download_flat(cuda_ps.values()), cpu_ps.download_flat(cpu_ps.values()));

  const TinyData data = tiny_data(c, 2, 21);
  for (LossKind kind : {LossKind::CrossEntropy, LossKind::Bce, LossKind::CrossEntropyLovasz}) {
    const char* kind_name = kind == LossKind::Bce                ? "bce"
                            : kind == LossKind::CrossEntropy ? "cross-entropy"
                                                             : "cross-entropy + Lovász";
    SCOPED_TRACE(kind_name);
    cpu_net.forward(data.batch, true);
    cuda_net.forward(data.batch, true);
    EXPECT_TRUE(test::all_close(cuda_net.download_logits(), cpu_net.download_logits(), kForwardAtol,
                                kForwardRtol));
    const double cpu_loss = cpu_net.loss(data.labels, kind, kCoefficients);
    const double cuda_loss = cuda_net.loss(data.labels, kind, kCoefficients);
    EXPECT_NEAR(cuda_loss, cpu_loss, kLossRtol * std::abs(cpu_loss));
    cpu_net.backward();
    cuda_net.backward();
    // atol: relative to the tensor's own scale, with a floor for the convolution biases ahead
    // of a BatchNorm, whose true gradient is 0 (the normalisation removes any shift): both
    // backends give rounding noise of about 1e-8 there.
    int compared = 0;
    for (int i = 0; i < static_cast<int>(cpu_ps.entries().size()); ++i) {
      const ParamEntry& e = cpu_ps.entries()[static_cast<size_t>(i)];
      if (!e.trainable) continue;
      Tensor<float> cpu_grad(e.shape), cuda_grad(e.shape);
      cpu->download(cpu_grad.data(), cpu_ps.grad(i).data, cpu_grad.numel() * sizeof(float));
      cuda.download(cuda_grad.data(), cuda_ps.grad(i).data, cuda_grad.numel() * sizeof(float));
      const double atol = kGradientAtolScale * max_abs(cpu_grad) + kGradientAtolFloor;
      EXPECT_TRUE(test::all_close(cuda_grad, cpu_grad, atol, kGradientRtol)) << e.name;
      if (max_abs(cpu_grad) > 1e-4) ++compared;
    }
    EXPECT_GT(compared, 20) << "tensors with gradients well above rounding noise";
    // Running statistics (moved by both training forwards so far) and their counters.
    EXPECT_TRUE(test::all_close(as_tensor(cuda_ps.download_flat(cuda_ps.buffers())),
                                as_tensor(cpu_ps.download_flat(cpu_ps.buffers())), 1e-6, 1e-5));
    EXPECT_EQ(cuda_ps.counters(), cpu_ps.counters());
  }

  // One AdamW step from the same gradients (the CPU's: a first step moves each parameter by
  // about lr sign(g), so a gradient near 0 whose sign the backends disagree on would move it by
  // 2 lr the other way) and the same parameters.
  cuda_ps.upload_flat(cuda_ps.grads(), cpu_ps.download_flat(cpu_ps.grads()));
  cuda_ps.upload_flat(cuda_ps.values(), cpu_ps.download_flat(cpu_ps.values()));
  adam(*cpu, cpu_ps, 1);
  adam(cuda, cuda_ps, 1);
  // The same float formula on both sides: the parameters (O(0.1)) agree to about their ulp, the
  // moments to a relative ulp or two.
  struct State {
    const char* name;
    Ref cuda, cpu;
    double atol;
  };
  const State states[] = {{"parameters", cuda_ps.values(), cpu_ps.values(), 1e-7},
                          {"exp_avg", cuda_ps.adam_m(), cpu_ps.adam_m(), 1e-12},
                          {"exp_avg_sq", cuda_ps.adam_v(), cpu_ps.adam_v(), 1e-15}};
  for (const State& state : states) {
    EXPECT_TRUE(test::all_close(as_tensor(cuda_ps.download_flat(state.cuda)),
                                as_tensor(cpu_ps.download_flat(state.cpu)), state.atol, 1e-6))
        << state.name;
  }

  // Evaluation with the running statistics (through the recorded graph on the CUDA side).
  cpu_net.forward(data.batch, false);
  cuda_net.forward(data.batch, false);
  EXPECT_EQ(cuda.stats().graph_replays, 1);
  const Tensor<float> cpu_logits = cpu_net.download_logits();
  EXPECT_TRUE(test::all_close(cuda_net.download_logits(), cpu_logits, kForwardAtol, kForwardRtol));
  EXPECT_TRUE(test::all_close(cuda_net.probabilities(), cpu_net.probabilities(), 1e-7, 2e-5));
  // Class maps agree wherever the top two logits are apart by more than the tolerance.
  const Tensor<uint8_t> cpu_labels = cpu_net.predict_labels(),
                        cuda_labels = cuda_net.predict_labels();
  ASSERT_EQ(cuda_labels.shape(), cpu_labels.shape());
  const int64_t K = cpu_logits.dim(1), S = cpu_logits.dim(2) * cpu_logits.dim(3);
  int64_t decided = 0;
  for (int64_t b = 0; b < cpu_logits.dim(0); ++b) {
    for (int64_t s = 0; s < S; ++s) {
      std::vector<float> z(static_cast<size_t>(K));
      for (int64_t k = 0; k < K; ++k)
        z[static_cast<size_t>(k)] = cpu_logits.data()[(b * K + k) * S + s];
      std::vector<float> sorted = z;
      std::sort(sorted.begin(), sorted.end(), std::greater<>());
      const int64_t cell = b * S + s;
      if (sorted[0] - sorted[1] <= 1e-4 * (1 + std::abs(sorted[0]))) continue;
      ++decided;
      EXPECT_EQ(cuda_labels.data()[cell], cpu_labels.data()[cell]) << "cell " << cell;
    }
  }
  EXPECT_GT(decided, cpu_labels.numel() * 9 / 10);
}

INSTANTIATE_TEST_SUITE_P(Variants, CudaBackendModel, ::testing::ValuesIn(kVariants),
                         [](const ::testing::TestParamInfo<Variant>& case_info) {
                           return std::string(case_info.param.name);
                         });

// The recorded evaluation forward against the same model run op by op on a backend with graphs
// off: the same kernels on the same data, so the same bits.
TEST(CudaBackendGraph, ReplayMatchesTheUncapturedForward) {
  const ModelConfig c = tiny_config(OccupancyInput::Observability2D, /*transposed=*/false);
  CudaBackendOptions no_graphs;
  no_graphs.graphs = false;
  CudaBackend graphed, direct(no_graphs);
  ASSERT_TRUE(graphed.supports_capture());
  ASSERT_FALSE(direct.supports_capture());
  PillarSegNet graph_net(c, graphed, 3), direct_net(c, direct, 3);
  // A training step first, so that the running statistics are not their initial values.
  const TinyData train = tiny_data(c, 2, 1);
  for (PillarSegNet* net : {&graph_net, &direct_net}) {
    net->forward(train.batch, true);
    net->loss(train.labels, LossKind::CrossEntropy, kCoefficients);
    net->backward();
    adam(net->backend(), net->parameters(), 1);
  }
  const auto expect_same = [&](const ModelBatch& batch, const char* what) {
    graph_net.forward(batch, false);
    direct_net.forward(batch, false);
    EXPECT_EQ(graph_net.download_logits(), direct_net.download_logits()) << what;
    EXPECT_EQ(graph_net.predict_labels(), direct_net.predict_labels()) << what;
  };
  const TinyData dense = tiny_data(c, 2, 2, 0.5), sparse = tiny_data(c, 2, 3, 0.1);
  ASSERT_GT(dense.batch.pillar_points.dim(0), 2 * sparse.batch.pillar_points.dim(0));
  expect_same(dense.batch, "first replay");
  EXPECT_EQ(graphed.stats().graphs_captured, 1);
  // Fewer pillars than last time: the rows the dense scan filled must not reach the canvas.
  expect_same(sparse.batch, "fewer pillars");
  ModelBatch no_pillars = sparse.batch;
  no_pillars.pillar_points = Tensor<float>({0, c.max_points_per_pillar, 10});
  no_pillars.pillar_cells = Tensor<int32_t>({0, 3});
  expect_same(no_pillars, "no pillars");
  EXPECT_EQ(graphed.stats().graphs_captured, 1);
  EXPECT_EQ(graphed.stats().graph_replays, 3);
  // The graph reads the parameters at replay time.
  for (PillarSegNet* net : {&graph_net, &direct_net}) {
    net->forward(train.batch, true);
    net->loss(train.labels, LossKind::Bce, kCoefficients);
    net->backward();
    adam(net->backend(), net->parameters(), 2);
  }
  expect_same(dense.batch, "after a parameter update");
  EXPECT_EQ(graphed.stats().graphs_captured, 1);
  // A new batch size with more pillars than the capacity re-plans and records again.
  const TinyData bigger = tiny_data(c, 3, 4, 1.0);
  ASSERT_GT(bigger.batch.pillar_points.dim(0), 1024);
  expect_same(bigger.batch, "after a re-plan");
  EXPECT_EQ(graphed.stats().graphs_captured, 2);
  // Stage timing runs the forward op by op (it waits between stages) with the same result.
  graph_net.set_stage_timing(true);
  expect_same(bigger.batch, "with stage timing");
  EXPECT_EQ(graphed.stats().graphs_captured, 2);
  EXPECT_EQ(graphed.stats().graph_replays, 5);
  const auto& st = graph_net.stage_times();
  for (double t : {st.upload, st.pfn, st.scatter, st.occupancy, st.unet, st.head})
    EXPECT_GE(t, 0.0);
}

TEST(CudaBackendGraph, CaptureRefusesHostWorkAndLeavesTheBackendUsable) {
  CudaBackend backend;
  void* device = backend.allocate(64);
  const std::vector<float> host(16, 1.5f);
  try {
    backend.capture([&] { backend.upload(device, host.data(), 64); });
    FAIL() << "an upload inside a capture must throw";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("while a graph is being captured"), std::string::npos)
        << e.what();
  }
  // The stream captures no more: work runs again, and a capture of device work replays.
  backend.upload(device, host.data(), 64);
  std::vector<float> back(16, 0.0f);
  backend.download(back.data(), device, 64);
  EXPECT_EQ(back, host);
  const auto graph = backend.capture([&] { backend.fill_zero(device, 64); });
  backend.download(back.data(), device, 64);
  EXPECT_EQ(back, host) << "capturing must not run the work";
  graph->replay();
  backend.download(back.data(), device, 64);
  EXPECT_EQ(back, std::vector<float>(16, 0.0f));
  backend.deallocate(device);
}

TEST(CudaBackendMemory, SteadyStateTrainingAllocatesNothing) {
  const ModelConfig c = tiny_config(OccupancyInput::Observability2D, /*transposed=*/false);
  CudaBackend backend;
  PillarSegNet net(c, backend, 5);
  ParameterSet& ps = net.parameters();
  const TinyData first = tiny_data(c, 2, 10, 0.4), later = tiny_data(c, 2, 11, 0.2);
  const auto step = [&](const TinyData& d, int64_t t) {
    net.forward(d.batch, true);
    net.loss(d.labels, LossKind::CrossEntropy, kCoefficients);
    net.backward();
    const double norm = std::sqrt(backend.sum_of_squares(ps.grads()));
    Ref grads = ps.grads();
    backend.scale(grads, static_cast<float>(1.0 / (norm + 1e-6)));
    adam(backend, ps, t);
    net.forward(d.batch, false);  // validation
    net.predict_labels();
  };
  step(first, 1);
  const CudaBackendStats warm = backend.stats();
  const size_t activation_bytes = net.activation_bytes();
  EXPECT_GT(warm.device_allocations, 0);
  EXPECT_GT(warm.workspace_bytes, 0u);
  for (int64_t t = 2; t <= 4; ++t) step(t % 2 == 0 ? later : first, t);
  const CudaBackendStats steady = backend.stats();
  EXPECT_EQ(steady.device_allocations, warm.device_allocations);
  EXPECT_EQ(steady.pinned_allocations, warm.pinned_allocations);
  EXPECT_EQ(steady.workspace_bytes, warm.workspace_bytes);
  EXPECT_EQ(steady.staging_bytes, warm.staging_bytes);
  EXPECT_EQ(steady.graphs_captured, 1);
  EXPECT_EQ(net.activation_bytes(), activation_bytes);
}

TEST(CudaBackendMemory, UploadsLargerThanTheStagingBufferArriveWhole) {
  CudaBackendOptions small;
  small.max_staging_bytes = 1024;
  CudaBackend backend(small);
  std::vector<float> host(10007);  // 40028 bytes: 40 pieces, the last one partial
  for (size_t i = 0; i < host.size(); ++i) host[i] = static_cast<float>(i) * 0.25f - 7.0f;
  void* device = backend.allocate(host.size() * sizeof(float));
  backend.upload(device, host.data(), host.size() * sizeof(float));
  std::vector<float> back(host.size());
  backend.download(back.data(), device, back.size() * sizeof(float));
  EXPECT_EQ(back, host);
  EXPECT_EQ(backend.stats().staging_bytes, 1024u);
  EXPECT_EQ(backend.stats().readback_bytes, 1024u);
  EXPECT_EQ(backend.stats().bytes_uploaded, 40028);
  EXPECT_EQ(backend.stats().bytes_downloaded, 40028);
  backend.deallocate(device);

  // The whole model through the small staging buffer: the same bits as through a large one.
  const ModelConfig c = tiny_config(OccupancyInput::Occupancy3D, /*transposed=*/false);
  CudaBackend large;
  PillarSegNet small_net(c, backend, 2), large_net(c, large, 2);
  const TinyData data = tiny_data(c, 2, 8);
  small_net.forward(data.batch, true);
  large_net.forward(data.batch, true);
  EXPECT_EQ(small_net.download_logits(), large_net.download_logits());
  EXPECT_EQ(small_net.loss(data.labels, LossKind::Bce, kCoefficients),
            large_net.loss(data.labels, LossKind::Bce, kCoefficients));
}

TEST(CudaBackendErrors, SayWhatIsWrong) {
  const auto message_of = [](const auto& fn) {
    try {
      fn();
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string("(no error)");
  };
  // A program that did not install the CUDA backends (the engine alone).
  EXPECT_NE(message_of([] { make_backend("cuda"); }).find("this build has no CUDA backend"),
            std::string::npos);
  EXPECT_NE(message_of([] { make_backend("emu"); }).find("no emulated CUDA backend"),
            std::string::npos);
  EXPECT_NE(message_of([] { make_backend("tpu"); }).find("--device must be cpu, cuda or emu"),
            std::string::npos);
  EXPECT_EQ(available_devices(), "cpu");
  install_this_cuda_backend();
  EXPECT_EQ(available_devices(), std::string("cpu, ") + kCudaBackendDevice);
  const auto backend = make_backend(kCudaBackendDevice);
  EXPECT_EQ(backend->device(), Device::Cuda);
  EXPECT_EQ(backend->name().rfind(std::string(kCudaBackendDevice) + ":0 (", 0), 0u) << backend->name();
  BackendOptions missing_device;
  missing_device.cuda_device = 7;
  EXPECT_NE(message_of([&] { make_backend(kCudaBackendDevice, missing_device); })
                .find("CUDA device 7 does not exist"),
            std::string::npos);
  set_backend_factory(kCudaBackendDevice, nullptr);

  // What CudaBackend throws on a machine whose runtime finds no GPU.
  const std::string no_device = no_cuda_device_message(cudaErrorNoDevice, 0);
  EXPECT_EQ(no_device.rfind("no CUDA device found: ", 0), 0u) << no_device;
  EXPECT_NE(no_device.find("cudaErrorNoDevice"), std::string::npos) << no_device;
  EXPECT_NE(no_device.find("--device cpu"), std::string::npos) << no_device;
  EXPECT_NE(no_cuda_device_message(cudaSuccess, 0).find("reports 0 devices"), std::string::npos);

  // Shapes are checked at the API edge, naming the op and both shapes.
  CudaBackend cuda;
  Arena arena(cuda);
  arena.reserve(1 << 16);
  Ref x = arena.take<float>({1, 2, 5, 5}), w = arena.take<float>({3, 2, 3, 3});
  Ref y = arena.take<float>({1, 3, 4, 4});
  const std::string conv = message_of([&] { cuda.conv2d_forward(x, w, nullptr, 1, y); });
  EXPECT_NE(conv.find("conv2d_forward: y must be (1, 3, 5, 5), got (1, 3, 4, 4)"),
            std::string::npos)
      << conv;
  Ref coefficients = arena.take<float>({12});
  Ref logits = arena.take<float>({1, 12, 2, 2}), dlogits = arena.take<float>({1, 12, 2, 2});
  LRef labels = arena.take<uint8_t>({1, 2, 2});
  const std::string loss =
      message_of([&] { cuda.loss(LossKind::Bce, logits, labels, coefficients, dlogits); });
  EXPECT_NE(loss.find("coefficients"), std::string::npos) << loss;
  EXPECT_NE(loss.find("(13)"), std::string::npos) << loss;
}

TEST(CudaBackendClock, IsMonotoneAndWaitsForTheWork) {
  CudaBackend backend;
  const double t0 = backend.clock_ms();
  void* device = backend.allocate(1 << 20);
  backend.fill_zero(device, 1 << 20);
  const double t1 = backend.clock_ms();
  const double t2 = backend.clock_ms();
  EXPECT_LE(t0, t1);
  EXPECT_LE(t1, t2);
  backend.deallocate(device);
}

// ---- cuDNN and cuBLAS convolutions (CudaBackendOptions::convolution) ----

#if defined(PILLARSEG_CUDA_EMULATION)

// The emulation has our kernels only: asking for a vendor library says so, through the options
// and through the factory behind --conv.
TEST(CudaBackendVendorConv, EmulatedBuildRefusesCudnnAndCublas) {
  for (ConvolutionImpl impl : {ConvolutionImpl::Cudnn, ConvolutionImpl::Cublas}) {
    CudaBackendOptions options;
    options.convolution = impl;
    try {
      CudaBackend backend(options);
      FAIL() << "the emulated backend must refuse --conv " << convolution_impl_name(impl);
    } catch (const Error& e) {
      const std::string message = e.what();
      EXPECT_NE(message.find(std::string("--conv ") + convolution_impl_name(impl) +
                             " needs the GPU build"),
                std::string::npos)
          << message;
      EXPECT_NE(message.find("use --conv own"), std::string::npos) << message;
    }
  }
  install_this_cuda_backend();
  EXPECT_THROW(make_backend("emu", {"cublas", 0}), Error);
  EXPECT_EQ(make_backend("emu", {"own", 0})->device(), Device::Cuda);
  set_backend_factory("emu", nullptr);
}

#else

namespace {

CudaBackendOptions with_convolution(ConvolutionImpl impl) {
  CudaBackendOptions options;
  options.convolution = impl;
  return options;
}

// One Conv2d's inputs and results on one backend.
struct ConvRun {
  Tensor<float> y, dx, dw, db;
};

// Forward and backward of x (B, I, H, W), w (O, I, k, k), bias (O) on `backend`, from host
// tensors; also checks that a second run gives the same bits (every implementation is
// deterministic).
ConvRun run_conv(CudaBackend& backend, const Tensor<float>& x, const Tensor<float>& w,
                 const Tensor<float>& bias, const Tensor<float>& dy, int pad, bool with_bias) {
  struct Refs {
    Ref x, w, bias, dy, y, dx, dw, db;
  };
  Arena arena(backend);
  const auto take_all = [&] {
    arena.reset();
    return Refs{arena.take<float>(x.shape()),    arena.take<float>(w.shape()),
                arena.take<float>(bias.shape()), arena.take<float>(dy.shape()),
                arena.take<float>(dy.shape()),   arena.take<float>(x.shape()),
                arena.take<float>(w.shape()),    arena.take<float>(bias.shape())};
  };
  arena.begin_measure();
  take_all();
  arena.reserve(arena.used());
  Refs r = take_all();
  backend.upload(r.x.data, x.data(), x.numel() * sizeof(float));
  backend.upload(r.w.data, w.data(), w.numel() * sizeof(float));
  backend.upload(r.bias.data, bias.data(), bias.numel() * sizeof(float));
  backend.upload(r.dy.data, dy.data(), dy.numel() * sizeof(float));
  ConvRun first;
  for (int repeat = 0; repeat < 2; ++repeat) {
    backend.conv2d_forward(r.x, r.w, with_bias ? &r.bias : nullptr, pad, r.y);
    backend.conv2d_backward(r.x, r.w, r.dy, pad, &r.dx, r.dw, with_bias ? &r.db : nullptr);
    ConvRun run{Tensor<float>(dy.shape()), Tensor<float>(x.shape()), Tensor<float>(w.shape()),
                Tensor<float>(bias.shape())};
    backend.download(run.y.data(), r.y.data, r.y.bytes());
    backend.download(run.dx.data(), r.dx.data, r.dx.bytes());
    backend.download(run.dw.data(), r.dw.data, r.dw.bytes());
    if (with_bias) backend.download(run.db.data(), r.db.data, r.db.bytes());
    if (repeat == 0) {
      first = std::move(run);
    } else {
      EXPECT_EQ(run.y, first.y) << backend.name() << ": forward not deterministic";
      EXPECT_EQ(run.dx, first.dx) << backend.name() << ": dx not deterministic";
      EXPECT_EQ(run.dw, first.dw) << backend.name() << ": dw not deterministic";
      EXPECT_EQ(run.db, first.db) << backend.name() << ": db not deterministic";
    }
  }
  return first;
}

struct ConvCase {
  const char* name;
  int64_t B, I, H, W, O, k, pad;
  bool bias;
};

// The U-Net's kinds of layers, small: 3x3 with bias (double convs), the occupancy convolution
// (no bias), the 1x1 head, odd sizes, and a single-row image.
const ConvCase kConvCases[] = {
    {"double_conv_3x3", 2, 8, 12, 20, 16, 3, 1, true},
    {"occupancy_no_bias", 2, 20, 8, 10, 3, 3, 1, false},
    {"head_1x1", 2, 8, 7, 9, 12, 1, 0, true},
    {"odd_sizes", 1, 5, 9, 13, 7, 3, 1, true},
    {"single_row", 3, 3, 1, 11, 4, 3, 1, true},
};

}  // namespace

// Each vendor path against ours at every case: y, dx, dw, db. Both sum up to a few hundred FP32
// products per output in different orders, and cuDNN may transform (Winograd, FFT), which rounds
// differently again: differences of at most about 1e-6 of the output's scale; an indexing error
// would be of the order of the scale.
constexpr double kPassAtolScale = 1e-5, kPassRtol = 1e-4;

TEST(CudaBackendVendorConv, PassesMatchOurKernels) {
  CudaBackend own;
  CudaBackend cudnn(with_convolution(ConvolutionImpl::Cudnn));
  CudaBackend cublas(with_convolution(ConvolutionImpl::Cublas));
  // cuBLAS with a cols buffer of two output rows of the largest case: the lowering runs in bands
  // (and a partial last band), whose col2im contributions overlap in dx.
  CudaBackendOptions banded_options = with_convolution(ConvolutionImpl::Cublas);
  banded_options.vendor.workspace_limit_bytes = 2 * 20 * 9 * 10 * sizeof(float);
  CudaBackend banded(banded_options);
  EXPECT_NE(cudnn.name().find("cudnn convolutions"), std::string::npos) << cudnn.name();
  Rng rng(17);
  for (const ConvCase& c : kConvCases) {
    SCOPED_TRACE(c.name);
    const int64_t Ho = c.H + 2 * c.pad - c.k + 1, Wo = c.W + 2 * c.pad - c.k + 1;
    const Tensor<float> x = test::random_tensor<float>({c.B, c.I, c.H, c.W}, rng);
    const Tensor<float> w = test::random_tensor<float>({c.O, c.I, c.k, c.k}, rng);
    const Tensor<float> bias = test::random_tensor<float>({c.O}, rng);
    const Tensor<float> dy = test::random_tensor<float>({c.B, c.O, Ho, Wo}, rng);
    const ConvRun expected = run_conv(own, x, w, bias, dy, static_cast<int>(c.pad), c.bias);
    for (CudaBackend* vendor : {&cudnn, &cublas, &banded}) {
      SCOPED_TRACE(vendor->name());
      const ConvRun got = run_conv(*vendor, x, w, bias, dy, static_cast<int>(c.pad), c.bias);
      EXPECT_TRUE(
          test::all_close(got.y, expected.y, kPassAtolScale * max_abs(expected.y), kPassRtol))
          << "y";
      EXPECT_TRUE(
          test::all_close(got.dx, expected.dx, kPassAtolScale * max_abs(expected.dx), kPassRtol))
          << "dx";
      EXPECT_TRUE(
          test::all_close(got.dw, expected.dw, kPassAtolScale * max_abs(expected.dw), kPassRtol))
          << "dw";
      if (c.bias) {
        EXPECT_TRUE(
            test::all_close(got.db, expected.db, kPassAtolScale * max_abs(expected.db), kPassRtol))
            << "db";
      }
    }
  }
  // The banded cuBLAS engine never grows its buffers; cuDNN planned each shape once.
  EXPECT_EQ(banded.stats().vendor_conv.device_allocations, 2);
  EXPECT_EQ(cudnn.stats().vendor_conv.plans, static_cast<int64_t>(std::size(kConvCases)));
}

// The whole tiny model on each vendor path against ours (both on the GPU): training forward,
// loss, every gradient, then the evaluation forward, which the backend records as a graph, and
// a steady state that allocates nothing more. Tolerances: those against the CPU backend, times
// kVendorSlack for cuDNN's transforms (see PassesMatchOurKernels), amplified like any
// difference by training-mode BatchNorm.
constexpr double kVendorSlack = 10;
class CudaBackendVendorModel : public ::testing::TestWithParam<ConvolutionImpl> {};

TEST_P(CudaBackendVendorModel, MatchesOurConvolutions) {
  const ModelConfig c = tiny_config(OccupancyInput::Observability2D, /*transposed=*/false);
  CudaBackend own, vendor(with_convolution(GetParam()));
  PillarSegNet own_net(c, own, 7), vendor_net(c, vendor, 7);
  ParameterSet &own_ps = own_net.parameters(), &vendor_ps = vendor_net.parameters();
  const TinyData data = tiny_data(c, 2, 31);
  for (int step = 1; step <= 2; ++step) {
    SCOPED_TRACE(step);
    own_net.forward(data.batch, true);
    vendor_net.forward(data.batch, true);
    EXPECT_TRUE(test::all_close(vendor_net.download_logits(), own_net.download_logits(),
                                kVendorSlack * kForwardAtol, kVendorSlack * kForwardRtol));
    const double own_loss = own_net.loss(data.labels, LossKind::CrossEntropy, kCoefficients);
    const double vendor_loss = vendor_net.loss(data.labels, LossKind::CrossEntropy, kCoefficients);
    EXPECT_NEAR(vendor_loss, own_loss, kVendorSlack * kLossRtol * std::abs(own_loss));
    own_net.backward();
    vendor_net.backward();
    for (int i = 0; i < static_cast<int>(own_ps.entries().size()); ++i) {
      const ParamEntry& e = own_ps.entries()[static_cast<size_t>(i)];
      if (!e.trainable) continue;
      Tensor<float> own_grad(e.shape), vendor_grad(e.shape);
      own.download(own_grad.data(), own_ps.grad(i).data, own_grad.numel() * sizeof(float));
      vendor.download(vendor_grad.data(), vendor_ps.grad(i).data,
                      vendor_grad.numel() * sizeof(float));
      const double atol =
          kVendorSlack * (kGradientAtolScale * max_abs(own_grad) + kGradientAtolFloor);
      EXPECT_TRUE(test::all_close(vendor_grad, own_grad, atol, kVendorSlack * kGradientRtol))
          << e.name;
    }
    // The same update on both sides (from our gradients), so step 2 starts level again.
    vendor_ps.upload_flat(vendor_ps.grads(), own_ps.download_flat(own_ps.grads()));
    adam(own, own_ps, step);
    adam(vendor, vendor_ps, step);
    own_net.forward(data.batch, false);
    vendor_net.forward(data.batch, false);
    EXPECT_TRUE(test::all_close(vendor_net.download_logits(), own_net.download_logits(),
                                kVendorSlack * kForwardAtol, kVendorSlack * kForwardRtol))
        << "evaluation (graph replay)";
  }
  EXPECT_EQ(vendor.stats().graphs_captured, 1);
  EXPECT_EQ(vendor.stats().graph_replays, 2);
  // A third step allocates nothing: algorithms, plans and workspaces were settled by the first.
  const CudaBackendStats settled = vendor.stats();
  vendor_net.forward(data.batch, true);
  vendor_net.loss(data.labels, LossKind::Bce, kCoefficients);
  vendor_net.backward();
  vendor_net.forward(data.batch, false);
  vendor.synchronize();
  EXPECT_EQ(vendor.stats().device_allocations, settled.device_allocations);
  EXPECT_EQ(vendor.stats().vendor_conv.device_allocations, settled.vendor_conv.device_allocations);
  EXPECT_EQ(vendor.stats().vendor_conv.workspace_bytes, settled.vendor_conv.workspace_bytes);
}

INSTANTIATE_TEST_SUITE_P(Impls, CudaBackendVendorModel,
                         ::testing::Values(ConvolutionImpl::Cudnn, ConvolutionImpl::Cublas),
                         [](const ::testing::TestParamInfo<ConvolutionImpl>& case_info) {
                           return std::string(convolution_impl_name(case_info.param));
                         });

// ---- the data-parallel gradient sum over NCCL ----

// One GPU holds one NCCL rank, and one rank runs the whole path of the sum: NCCL loaded, the
// communicator made from an id sent through the Replicas, grouped send and receive to itself, the
// replica-order sum kernel, the all-gather, all on the sums' own stream. That stream must wait for
// the compute stream's work queued before begin (the values set to NaN, a large upload, then the
// values): a sum that ran early would write NaN or a partial copy back. After end(), the compute
// stream's download must see the summed values: for one rank, the values themselves, bit for bit.
// Skips where NCCL cannot be loaded.
TEST(CudaBackendReplicas, OneRankNcclSumRunsBehindTheComputeStream) {
  CudaBackend backend;
  SingleProcess one_rank;
  const int64_t n = (int64_t{3} << 20) + 5;
  std::vector<float> host(static_cast<size_t>(n));
  for (size_t i = 0; i < host.size(); ++i) host[i] = static_cast<float>(i % 1013) * 0.125f - 60.0f;
  const size_t bytes = host.size() * sizeof(float);
  const std::vector<char> big_host(size_t{256} << 20, 1);
  void* values = backend.allocate(bytes);
  void* big = backend.allocate(big_host.size());
  for (int round = 0; round < 2; ++round) {  // the second reuses the communicator and scratch
    ASSERT_EQ(cudaMemsetAsync(values, 0xff, bytes, backend.stream()), cudaSuccess);
    backend.upload(big, big_host.data(), big_host.size());
    backend.upload(values, host.data(), bytes);
    Ref piece{static_cast<float*>(values), {n}};
    try {
      backend.begin_sum_over_replicas(piece, one_rank);
    } catch (const Error& e) {
      backend.deallocate(values);
      backend.deallocate(big);
      if (std::string(e.what()).find("cannot be loaded") != std::string::npos) GTEST_SKIP() << e.what();
      FAIL() << e.what();
    }
    backend.end_sums_over_replicas(one_rank);
    std::vector<float> back(host.size());
    backend.download(back.data(), values, bytes);
    ASSERT_EQ(std::memcmp(back.data(), host.data(), bytes), 0) << "round " << round;
  }
  backend.deallocate(values);
  backend.deallocate(big);
}

// Synchronised BatchNorm over NCCL with one rank: the backend given the run's Replicas sums the
// statistics with an ncclAllGather to itself and the replica-order add, between the combine's
// kernels, on the compute stream; given a ReplicaSum that is not a Replicas it keeps the host
// path (the sums brought to the host). Both run the combine's same per-channel code, so every
// output is bit for bit the host path's. Against no replicas: dgamma and dbeta are this
// replica's own sums from the same kernel, bit for bit; the statistics come from the same sums
// added in another order (parts in order rather than the finalize's warp tree) and the mean as
// (n shift + S1) / n rather than shift + S1 / n, equal in exact arithmetic, so in double they
// differ by a few units of 1e-16 relative and as floats by at most one ulp; y and dx follow from
// those floats within 2e-6 here (|x| and gamma of order 1). And nothing waits for the device: a
// host function holds the compute stream while the forward and backward are queued, and they
// return before the test lets it go (a watchdog lets it go after 10 s otherwise), the stream
// still busy; what the held run computes is again the same bits. Skips where NCCL cannot be
// loaded.
TEST(CudaBackendReplicas, OneRankNcclBatchNormStaysOnTheDevice) {
  CudaBackend backend;
  SingleProcess one_rank;
  struct OnlyASum final : ReplicaSum {  // one replica, summed on the host
    void sum(double*, int64_t) override {}
  } host_sum;
  const Shape shape{2, 40, 72, 64};
  const int64_t n = shape_numel(shape), channels = shape[1];
  Rng rng(2024);
  const Tensor<float> x = test::random_tensor<float>(shape, rng, -1.5, 2.5);
  const Tensor<float> dy = test::random_tensor<float>(shape, rng);
  const Tensor<float> gamma = test::random_tensor<float>({channels}, rng, 0.5, 1.5);
  const Tensor<float> beta = test::random_tensor<float>({channels}, rng);
  const Tensor<float> initial_mean = test::random_tensor<float>({channels}, rng);
  const Tensor<float> initial_var = test::random_tensor<float>({channels}, rng, 0.5, 2.0);
  std::vector<void*> owned;
  const auto tensor = [&](const Shape& s) {
    owned.push_back(backend.allocate(static_cast<size_t>(shape_numel(s)) * sizeof(float)));
    return Ref{static_cast<float*>(owned.back()), s};
  };
  Ref dx = tensor(shape), y = tensor(shape), dgamma = tensor({channels}),
      dbeta = tensor({channels});
  Ref x_ref = tensor(shape), dy_ref = tensor(shape);
  BatchNormRefs bn;
  bn.gamma = tensor({channels}), bn.beta = tensor({channels});
  bn.running_mean = tensor({channels}), bn.running_var = tensor({channels});
  bn.save_mean = tensor({channels}), bn.save_invstd = tensor({channels});
  const auto upload = [&](Ref& r, const Tensor<float>& t) {
    backend.upload(r.data, t.data(), static_cast<size_t>(t.numel()) * sizeof(float));
  };
  upload(x_ref, x), upload(dy_ref, dy), upload(bn.gamma, gamma), upload(bn.beta, beta);
  // A training forward and backward from the initial running statistics.
  const auto restart = [&] {
    upload(bn.running_mean, initial_mean), upload(bn.running_var, initial_var);
  };
  const auto queue_step = [&](ReplicaSum* replicas) {
    bn.replicas = replicas;
    backend.batchnorm_relu_forward(x_ref, bn, true, y);
    backend.batchnorm_relu_backward(x_ref, y, dy_ref, bn, dx, dgamma, dbeta);
  };
  const auto download = [&](const Ref& r) {
    std::vector<float> host(static_cast<size_t>(r.numel()));
    backend.download(host.data(), r.data, host.size() * sizeof(float));
    return host;
  };
  const auto outputs = [&] {
    return std::vector<std::vector<float> >{download(y),
                                            download(bn.save_mean),
                                            download(bn.save_invstd),
                                            download(bn.running_mean),
                                            download(bn.running_var),
                                            download(dx),
                                            download(dgamma),
                                            download(dbeta)};
  };
  const char* names[] = {"y",           "save_mean", "save_invstd", "running_mean",
                         "running_var", "dx",        "dgamma",      "dbeta"};
  const auto release = [&] {
    for (void* p : owned) backend.deallocate(p);
  };
  try {
    restart();
    queue_step(&one_rank);  // makes the communicator and the NCCL sum's scratch
  } catch (const Error& e) {
    release();
    if (std::string(e.what()).find("cannot be loaded") != std::string::npos)
      GTEST_SKIP() << e.what();
    FAIL() << e.what();
  }
  const std::vector<std::vector<float> > on_device = outputs();
  restart();
  queue_step(&host_sum);
  const std::vector<std::vector<float> > on_host = outputs();
  restart();
  queue_step(nullptr);
  const std::vector<std::vector<float> > alone = outputs();
  const auto same_bits = [](const std::vector<float>& a, const std::vector<float>& b) {
    return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
  };
  const auto within_one_ulp = [](const std::vector<float>& a, const std::vector<float>& b) {
    for (size_t i = 0; i < a.size(); ++i) {
      if (a[i] != b[i] && std::nextafter(b[i], a[i]) != a[i]) return false;
    }
    return a.size() == b.size();
  };
  for (size_t i = 0; i < on_device.size(); ++i) {
    EXPECT_TRUE(same_bits(on_device[i], on_host[i])) << names[i] << ": NCCL path against host path";
  }
  EXPECT_TRUE(same_bits(on_device[6], alone[6])) << "dgamma: this replica's own sums";
  EXPECT_TRUE(same_bits(on_device[7], alone[7])) << "dbeta: this replica's own sums";
  for (size_t i = 1; i <= 4; ++i) EXPECT_TRUE(within_one_ulp(on_device[i], alone[i])) << names[i];
  EXPECT_TRUE(test::all_close(on_device[0].data(), alone[0].data(), n, 2e-6, 2e-6)) << "y";
  EXPECT_TRUE(test::all_close(on_device[5].data(), alone[5].data(), n, 2e-6, 2e-6)) << "dx";

  restart();
  std::atomic<bool> open{false}, queued{false};
  PS_CUDA_CHECK(cudaLaunchHostFunc(
      backend.stream(),
      [](void* gate) {
        while (!static_cast<std::atomic<bool>*>(gate)->load()) {
          std::this_thread::sleep_for(std::chrono::milliseconds(1));
        }
      },
      &open));
  std::thread watchdog([&] {
    for (int i = 0; i < 1000 && !queued.load(); ++i)
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    open = true;
  });
  queue_step(&one_rank);
  const bool returned_while_held = !open.load();
  const cudaError_t stream_state = cudaStreamQuery(backend.stream());
  queued = true;
  watchdog.join();
  EXPECT_TRUE(returned_while_held) << "a BatchNorm waited for the device";
  EXPECT_EQ(stream_state, cudaErrorNotReady);
  const std::vector<std::vector<float> > held = outputs();
  for (size_t i = 0; i < held.size(); ++i)
    EXPECT_TRUE(same_bits(held[i], on_device[i])) << names[i];
  release();
}

#endif  // PILLARSEG_CUDA_EMULATION

// Training in BF16 / FP16 (--precision on train): the convolutions' forward and both gradients
// on the tensor cores, everything else FP32. From the same initial parameters, the first step's
// loss and every gradient track the FP32 ones within the rounding of the operands; the graph
// holds no FP32 convolution; a few AdamW steps lower the loss as FP32 does; the CPU backend
// refuses.
TEST(CudaBackendPrecision, HalfTrainingTracksFp32) {
  for (const bool transposed : {false, true}) {
    for (const Precision precision : {Precision::BF16, Precision::F16}) {
      SCOPED_TRACE(std::string(transposed ? "transposed " : "bilinear ") + precision_name(precision));
      const ModelConfig c = tiny_config(OccupancyInput::Occupancy3D, transposed);
      const TinyData d = tiny_data(c, 2, 29, 0.4);
      CudaBackend backend32, backend16;
      PillarSegNet net32(c, backend32, 5), net16(c, backend16, 5);
      net16.set_training_precision(precision);
      EXPECT_EQ(net16.training_precision(), precision);
      EXPECT_EQ(net16.precision(), Precision::F32) << "the evaluation precision is separate";
      std::vector<double> losses32, losses16;
      for (int64_t step = 1; step <= 4; ++step) {
        for (PillarSegNet* net : {&net32, &net16}) {
          net->parameters().zero_grads();
          net->forward(d.batch, true);
          (net == &net32 ? losses32 : losses16).push_back(net->loss(d.labels, LossKind::CrossEntropy, kCoefficients));
          net->backward();
        }
        if (step == 1) {
          const std::vector<float> g32 = net32.parameters().download_flat(net32.parameters().grads());
          const std::vector<float> g16 = net16.parameters().download_flat(net16.parameters().grads());
          ASSERT_EQ(g32.size(), g16.size());
          double num = 0, den = 0;
          for (size_t i = 0; i < g32.size(); ++i) {
            const double e = static_cast<double>(g16[i]) - g32[i];
            num += e * e, den += static_cast<double>(g32[i]) * g32[i];
          }
          // The head's weight gradient takes one rounding of each operand: an NMSE of about
          // (2^-9)^2 (BF16) or (2^-12)^2 (FP16) times a few. Deeper, the BatchNorm backward's
          // cancellations and ReLU / max-pool choices that the forward's rounding flips add up.
          const int head = net32.parameters().find("segmentation_head.outc.conv.weight");
          ASSERT_GE(head, 0);
          const ParamEntry& e = net32.parameters().entries()[static_cast<size_t>(head)];
          double head_num = 0, head_den = 0;
          for (int64_t i = e.offset; i < e.offset + shape_numel(e.shape); ++i) {
            const double diff = static_cast<double>(g16[static_cast<size_t>(i)]) - g32[static_cast<size_t>(i)];
            head_num += diff * diff, head_den += static_cast<double>(g32[static_cast<size_t>(i)]) * g32[static_cast<size_t>(i)];
          }
          EXPECT_LT(head_num / head_den, precision == Precision::BF16 ? 1e-4 : 2e-6);
          RecordProperty(fmt::format("gradient_nmse_{}_{}", transposed ? "transposed" : "bilinear",
                                     precision_name(precision)),
                         fmt::format("{:.3g}", num / den));
          // Measured (emulation, 2026-12-02): 8.5e-3 / 1.2e-2 (bilinear / transposed) in BF16,
          // 4.5e-4 / 2.2e-3 in FP16; the head's 1.5e-5 in BF16.
          EXPECT_LT(num / den, precision == Precision::BF16 ? 3e-2 : 6e-3);
          EXPECT_GT(num / den, 0.0) << "the 16-bit path must round something";
          EXPECT_NEAR(losses16[0], losses32[0], 1e-2 * std::abs(losses32[0]));
        }
        adam(backend32, net32.parameters(), step);
        adam(backend16, net16.parameters(), step);
      }
      EXPECT_LT(losses16.back(), losses16.front()) << "training in 16 bits lowers the loss";
      EXPECT_NEAR(losses16.back(), losses32.back(), 0.05 * losses32.front());
      int half_backward = 0, fp32_convs = 0;
      for (const GraphNode& n : net16.graph(true).nodes()) {
        const bool backward = n.op == OpKind::Conv2dBackward || n.op == OpKind::ConvTranspose2dBackward;
        half_backward += backward && n.compute == (precision == Precision::BF16 ? DType::BF16 : DType::F16);
        fp32_convs += n.op == OpKind::Conv2d || n.op == OpKind::ConvTranspose2d || (backward && n.compute == DType::F32);
      }
      EXPECT_GT(half_backward, 0);
      EXPECT_EQ(fp32_convs, 0);
    }
  }
  auto cpu = make_cpu_backend();
  PillarSegNet on_cpu(tiny_config(), *cpu);
  try {
    on_cpu.set_training_precision(Precision::BF16);
    FAIL() << "the CPU backend trains in FP32 only";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("--precision bf16 for training: backend cpu trains in fp32 only"),
              std::string::npos)
        << e.what();
  }
}

// The names behind --conv, in both builds.
TEST(CudaBackendVendorConv, ConvolutionNamesParseAndRoundTrip) {
  for (ConvolutionImpl impl :
       {ConvolutionImpl::Own, ConvolutionImpl::Cudnn, ConvolutionImpl::Cublas}) {
    EXPECT_EQ(parse_convolution_impl(convolution_impl_name(impl)), impl);
  }
  try {
    parse_convolution_impl("mkl");
    FAIL() << "an unknown implementation must throw";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("--conv must be own, cudnn or cublas, got 'mkl'"),
              std::string::npos)
        << e.what();
  }
  // The CPU backend has one convolution.
  try {
    make_backend("cpu", {"cudnn", 0});
    FAIL() << "--conv cudnn with --device cpu must throw";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("--conv cudnn needs --device cuda"), std::string::npos)
        << e.what();
  }
}

// --precision bf16 / fp16: the evaluation forward's convolutions on the tensor cores (prepared
// 16-bit weights with the BatchNorm folded in, FP32 accumulation), against the FP32 forward of
// the same weights after a few training steps (so that BatchNorm statistics and weights are not
// at their initial values), for the bilinear and transposed U-Nets, replayed as a graph; the
// CPU backend refuses FP16 with the reason (its BF16: test_cpu_bf16).
TEST(CudaBackendPrecision, HalfEvaluationTracksFp32) {
  for (const bool transposed : {false, true}) {
    for (const Precision precision : {Precision::BF16, Precision::F16}) {
      SCOPED_TRACE(std::string(transposed ? "transposed " : "bilinear ") + precision_name(precision));
      const ModelConfig c = tiny_config(OccupancyInput::Occupancy3D, transposed);
      CudaBackend backend;
      PillarSegNet net(c, backend, 3);
      const TinyData d = tiny_data(c, 2, 21, 0.4);
      for (int64_t step = 1; step <= 3; ++step) {
        net.parameters().zero_grads();
        net.forward(d.batch, true);
        net.loss(d.labels, LossKind::CrossEntropy, kCoefficients);
        net.backward();
        adam(backend, net.parameters(), step);
      }
      net.forward(d.batch, false);
      const Tensor<float> fp32 = net.download_logits();
      const Tensor<uint8_t> labels32 = net.predict_labels();
      net.set_precision(precision);
      EXPECT_EQ(net.precision(), precision);
      net.forward(d.batch, false);
      net.forward(d.batch, false);  // replayed
      const Tensor<float> half = net.download_logits();
      const Tensor<uint8_t> labels16 = net.predict_labels();
      double num = 0, den = 0;
      for (int64_t i = 0; i < fp32.numel(); ++i) {
        const double e = static_cast<double>(half.data()[i]) - fp32.data()[i];
        num += e * e;
        den += static_cast<double>(fp32.data()[i]) * fp32.data()[i];
      }
      // Measured (emulation, 2026-12-01): NMSE 2.4e-7 (bilinear) and 1.7e-7 (transposed) in BF16,
      // 4.9e-9 and 2.6e-9 in FP16 (8x the precision: about 64x smaller squared errors).
      EXPECT_LT(num / den, precision == Precision::BF16 ? 1e-5 : 1e-7);
      EXPECT_GT(num / den, 0.0) << "the 16-bit path must round something";
      int64_t same = 0;
      for (int64_t i = 0; i < labels32.numel(); ++i) same += labels32.data()[i] == labels16.data()[i];
      EXPECT_GE(static_cast<double>(same), 0.99 * static_cast<double>(labels32.numel()));
      net.set_precision(Precision::F32);
      net.forward(d.batch, false);
      EXPECT_EQ(net.download_logits(), fp32) << "back to fp32 gives the fp32 logits bit for bit";
    }
  }
  // At full size (the paper's model, 1000 x 500) the U-Net's activations dominate the planned
  // evaluation block, and 16-bit ones shrink it (planned only: nothing runs).
  {
    CudaBackend backend;
    PillarSegNet full(ModelConfig{}, backend);
    full.prepare(1, 12000, false);
    const size_t fp32_bytes = full.graph(false).planned_bytes();
    full.set_precision(Precision::BF16);
    full.prepare(1, 12000, false);
    const size_t bf16_bytes = full.graph(false).planned_bytes();
    RecordProperty("full_size_eval_block_fp32_bytes", std::to_string(fp32_bytes));
    RecordProperty("full_size_eval_block_bf16_bytes", std::to_string(bf16_bytes));
    EXPECT_LT(static_cast<double>(bf16_bytes), 0.75 * static_cast<double>(fp32_bytes));
  }
  auto cpu = make_cpu_backend();
  PillarSegNet on_cpu(tiny_config(), *cpu);
  try {
    on_cpu.set_precision(Precision::F16);
    FAIL() << "the CPU backend has no FP16 convolutions";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("--precision fp16: the CPU backend has no FP16"), std::string::npos)
        << e.what();
  }
}

// The evaluation forward prepares its 16-bit weights once (into tensors of its plan that persist)
// and again only when the parameters change: a second forward runs no preparation and gives the
// same logits, also when replayed from the recorded graph; after a training step (Adam writing
// through values()), an upload of one tensor, or a precision change, the logits are those of a
// fresh model holding the same parameters.
TEST(CudaBackendPrecision, PreparedWeightsFollowTheParameters) {
  const ModelConfig c = tiny_config(OccupancyInput::Observability2D, /*transposed=*/true);
  const TinyData d = tiny_data(c, 1, 31, 0.4);
  CudaBackend backend;
  const auto fresh_logits = [&](const PillarSegNet& like, Precision precision) {
    PillarSegNet fresh(c, backend, 99);
    fresh.parameters().copy_values_from(like.parameters());
    fresh.set_precision(precision);
    fresh.forward(d.batch, false);
    return fresh.download_logits();
  };
  PillarSegNet net(c, backend, 3);
  net.set_precision(Precision::BF16);
  net.set_op_timing(true);  // runs the nodes one by one (no recording) and counts them
  net.forward(d.batch, false);
  const int64_t preparations = net.op_times().at("prepared weights bf16").calls;
  EXPECT_GT(preparations, 0);
  const Tensor<float> first = net.download_logits();
  net.forward(d.batch, false);
  EXPECT_EQ(net.op_times().at("prepared weights bf16").calls, preparations) << "prepared again, unchanged weights";
  EXPECT_EQ(net.download_logits(), first);
  net.set_op_timing(false);
  net.forward(d.batch, false);  // recorded
  net.forward(d.batch, false);  // replayed
  EXPECT_EQ(net.download_logits(), first);
  EXPECT_EQ(first, fresh_logits(net, Precision::BF16));

  const auto train_step = [&](int64_t step) {
    net.parameters().zero_grads();
    net.forward(d.batch, true);
    net.loss(d.labels, LossKind::CrossEntropy, kCoefficients);
    net.backward();
    adam(backend, net.parameters(), step);
  };
  train_step(1);  // plans the training step too
  net.forward(d.batch, false);
  const Tensor<float> trained_once = net.download_logits();
  EXPECT_NE(trained_once, first);
  EXPECT_EQ(trained_once, fresh_logits(net, Precision::BF16));
  train_step(2);  // nothing planned again: only the parameters' generation tells
  net.forward(d.batch, false);  // replayed after a preparation outside the recording
  const Tensor<float> trained = net.download_logits();
  EXPECT_NE(trained, trained_once);
  EXPECT_EQ(trained, fresh_logits(net, Precision::BF16));

  const int conv = net.parameters().find("segmentation_head.down1.maxpool_conv.1.double_conv.0.weight");
  ASSERT_GE(conv, 0);
  Tensor<float> doubled = net.parameters().download(conv);
  for (int64_t i = 0; i < doubled.numel(); ++i) doubled.data()[i] *= 2.0f;
  net.parameters().upload(conv, doubled);
  net.forward(d.batch, false);
  const Tensor<float> uploaded = net.download_logits();
  EXPECT_NE(uploaded, trained);
  EXPECT_EQ(uploaded, fresh_logits(net, Precision::BF16));

  net.set_precision(Precision::F16);
  net.forward(d.batch, false);
  EXPECT_EQ(net.download_logits(), fresh_logits(net, Precision::F16));
}
