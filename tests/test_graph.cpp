// The op graph and its lifetime planner (engine/model/graph.hpp): a hand-built graph's offsets
// and block size, and on every variant of the tiny model, for eval and training at batch 1 and
// 2, the planner's invariant: two tensors alive at the same node never share a byte, inputs
// are alive from the start, outputs to the end, and views lie inside their tensor. The gradient
// buckets of data-parallel training: a hand-built graph's, and on every variant that the backward
// hands each bucket out finished.
#include <gtest/gtest.h>

#include <climits>
#include <cstring>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "core/error.hpp"
#include "core/ops.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/model/roofline.hpp"
#include "tests/support/tiny_model.hpp"

using namespace pillarseg;

namespace {

GraphNode node(std::vector<int> reads, std::vector<int> writes) {
  GraphNode n;
  n.name = "n";
  n.reads = std::move(reads);
  n.writes = std::move(writes);
  return n;
}

}  // namespace

// a (nodes 0..1), b (1..2), c (2..3), d an input read at node 3. With 64-byte alignment a takes
// 256 bytes, b 128, c 200 -> 256, d 64. Largest first: a at 0; c (2..3) and a (0..1) are
// disjoint, so c shares a's bytes at 0; b (1..2) meets a and c: at 256; d (an input, alive from
// the start to node 3) meets all three: at 384. Block: 448.
TEST(Graph, PlansDisjointLifetimesIntoTheSameBytes) {
  Graph g;
  const int a = g.tensor("a", {64});
  const int b = g.tensor("b", {32});
  const int c = g.tensor("c", {50});
  const int d = g.tensor("d", {16});
  g.at(d).input = true;
  g.add(node({}, {a}));
  g.add(node({a}, {b}));
  g.add(node({b}, {c}));
  g.add(node({c, d}, {c}));
  EXPECT_EQ(g.plan(), 448u);
  EXPECT_EQ(g.at(a).offset, 0u);
  EXPECT_EQ(g.at(c).offset, 0u);
  EXPECT_EQ(g.at(b).offset, 256u);
  EXPECT_EQ(g.at(d).offset, 384u);
  EXPECT_EQ(g.lifetime(d), (std::pair<int, int>{-1, 3}));
  EXPECT_EQ(g.lifetime(b), (std::pair<int, int>{1, 2}));
}

TEST(Graph, OutputsLiveToTheEndAndViewsShareTheirTensor) {
  Graph g;
  const int a = g.tensor("a", {64});
  const int whole = g.tensor("whole", {64});
  const int half = g.view("whole.half", whole, {32}, 128);
  const int late = g.tensor("late", {64});
  g.at(a).output = true;
  g.add(node({}, {a}));
  g.add(node({}, {half}));
  g.add(node({half}, {late}));
  g.plan();
  EXPECT_EQ(g.lifetime(a).second, INT_MAX);
  EXPECT_EQ(g.lifetime(half), g.lifetime(whole));
  // `late` starts where `whole` ends (node 2): they meet, and `a` is alive throughout.
  EXPECT_NE(g.at(late).offset, g.at(whole).offset);
  EXPECT_NE(g.at(late).offset, g.at(a).offset);
  EXPECT_THROW(g.view("outside", whole, {32}, 160), Error);
}

// Least bytes of a node: distinct tensors read once plus distinct tensors written once, at their
// dtypes; a view counts its own bytes; dynamic rows take the run's pillar rows.
TEST(Graph, NodeBytesCountEachTensorReadAndWrittenOnce) {
  Graph g;
  const int x = g.tensor("x", {2, 3});                   // 24 bytes
  const int h = g.tensor("h", {5}, DType::BF16);         // 10
  const int whole = g.tensor("whole", {8});              // 32
  const int band = g.view("whole.band", whole, {2}, 8);  // 8
  const int rows = g.tensor("rows", {100, 4});           // planned at 100 rows of 16 bytes
  g.at(rows).dynamic_rows = true;
  g.add(node({x, h, x}, {band}));  // x once: 24 + 10 + 8
  g.add(node({band}, {band}));     // in place: read and written
  g.add(node({rows, x}, {h}));     // 7 rows: 112 + 24 + 10
  EXPECT_EQ(g.node_bytes(0, 7), 42u);
  EXPECT_EQ(g.node_bytes(1, 7), 16u);
  EXPECT_EQ(g.node_bytes(2, 7), 146u);
  EXPECT_EQ(g.node_bytes(2, 100), 1634u);
  // What a FillZero of each clears: its own bytes, at its dtype.
  EXPECT_EQ(g.tensor_bytes(h, 7), 10u);
  EXPECT_EQ(g.tensor_bytes(band, 7), 8u);
  EXPECT_EQ(g.tensor_bytes(rows, 7), 112u);
  // A channel copy and a scatter name the whole canvas but move a band or some cells: x (2 x 3
  // FP32) into a 16-bit canvas: 24 read + 12 written; 7 rows of 4 features and 7 cells of 3
  // int32 into the canvas: 112 + 84 read, 112 written.
  // (The records check shapes: x is (1, 2, 3, 1), a band of a (1, 4, 3, 1) canvas at channel 2;
  // the scatter's features (rows, 4) land in a (1, 4, 5, 50) canvas.)
  const int x4 = g.tensor("x4", {1, 2, 3, 1}, DType::BF16);  // 12 bytes
  const int canvas = g.tensor("canvas", {1, 4, 3, 1}, DType::BF16);
  GraphNode band_copy;
  band_copy.channel0 = 2;
  g.add(OpKind::CopyChannels, "copy", CopyChannelsArgs{.x = x4, .y = canvas}, band_copy);
  const int cells = g.tensor("cells", {100, 3}, DType::I32);
  g.at(cells).dynamic_rows = true;
  const int canvas16 = g.tensor("canvas16", {1, 4, 5, 50}, DType::BF16);
  g.add(OpKind::Scatter, "scatter", ScatterArgs{.features = rows, .cells = cells, .canvas = canvas16});
  EXPECT_EQ(g.node_bytes(3, 7), 24u);  // 12 read + 12 written
  // 112 + 84 read, 7 x 4 values written at 2 bytes
  EXPECT_EQ(g.node_bytes(4, 7), 252u);
  // The same scatter into an FP32 canvas writes 4 bytes a value.
  const int canvas32 = g.tensor("canvas32", {1, 4, 5, 50});
  g.add(OpKind::Scatter, "scatter32", ScatterArgs{.features = rows, .cells = cells, .canvas = canvas32});
  EXPECT_EQ(g.node_bytes(5, 7), 308u);
}

// A node's reads, writes and FLOPs come from its op's record; the record refuses a missing
// argument, a wrong dtype and a shape its rule does not give, naming the node.
TEST(Graph, RecordsDeriveAccessesAndCheckArguments) {
  Graph g;
  const int x = g.tensor("x", {1, 3, 8, 8}), w = g.tensor("w", {4, 3, 3, 3}), b = g.tensor("b", {4});
  const int y = g.tensor("y", {1, 4, 8, 8});
  GraphNode pad1;
  pad1.pad = 1;
  const GraphNode& conv = g.add(OpKind::Conv2d, "conv", Conv2dArgs{.x = x, .w = w, .bias = b, .y = y}, pad1);
  EXPECT_EQ(conv.reads, (std::vector<int>{x, w, b}));
  EXPECT_EQ(conv.writes, (std::vector<int>{y}));
  EXPECT_DOUBLE_EQ(conv.flops, 2.0 * 4 * 8 * 8 * 3 * 9);  // 2 x O x h x w x I x k k
  // In place: the add reads and writes a.
  const int d = g.tensor("d", {1, 4, 8, 8});
  const GraphNode& add = g.add(OpKind::AddInplace, "add", AddInplaceArgs{.a = y, .b = d});
  EXPECT_EQ(add.reads, (std::vector<int>{y, d}));
  EXPECT_EQ(add.writes, (std::vector<int>{y}));
  const auto message = [&](auto&& f) {
    try {
      f();
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string("accepted");
  };
  EXPECT_NE(message([&] { g.add(OpKind::Conv2d, "nox", Conv2dArgs{.w = w, .y = y}, pad1); }).find("lacks its argument x"),
            std::string::npos);
  EXPECT_NE(message([&] { g.add(OpKind::Conv2d, "nopad", Conv2dArgs{.x = x, .w = w, .y = y}); }).find("nopad"),
            std::string::npos)
      << "without padding y would be (1, 4, 6, 6)";
  const int x16 = g.tensor("x16", {1, 3, 8, 8}, DType::BF16);
  EXPECT_NE(message([&] { g.add(OpKind::Conv2d, "bf16", Conv2dArgs{.x = x16, .w = w, .y = y}, pad1); })
                .find("argument x (x16) is bf16"),
            std::string::npos);
  // A 16-bit max-pool needs no arg-max; an FP32 one does.
  const int p16 = g.tensor("p16", {1, 3, 4, 4}, DType::BF16), p32 = g.tensor("p32", {1, 3, 4, 4});
  EXPECT_EQ(message([&] { g.add(OpKind::MaxPool2d, "pool16", MaxPool2dArgs{.x = x16, .y = p16}); }), "accepted");
  EXPECT_NE(message([&] { g.add(OpKind::MaxPool2d, "pool32", MaxPool2dArgs{.x = x, .y = p32}); }).find("arg-max"),
            std::string::npos);
  EXPECT_NE(message([&] { g.add(OpKind::MaxPool2d, "mixed", MaxPool2dArgs{.x = x16, .y = p32}); }).find("mixed"),
            std::string::npos);
  // The label of a node says its dtype; the 16-bit convolutions run on the tensor cores.
  EXPECT_EQ(op_label(g, g.nodes()[0], Device::Cuda), "conv forward");
  EXPECT_EQ(op_label(g, g.nodes().back(), Device::Cuda), "maxpool forward bf16");
  EXPECT_FALSE(on_matrix_units(g, g.nodes()[0]));
}

// The roofline bound (engine/model/roofline.hpp) by hand: 2 GFLOP and 48 MB on custom peaks of
// 10 TFLOP/s FP32, 100 TFLOP/s 16-bit and 2 TB/s: on the tensor cores compute 0.02 ms < memory
// 0.024 ms (memory-bound); on the CUDA cores compute 0.2 ms (compute-bound).
TEST(Roofline, BoundsAnOpByItsFlopsAndBytes) {
  const GpuPeaks gpu = parse_gpu("custom:10:100:2");
  EXPECT_DOUBLE_EQ(gpu.fp32_tflops, 10);
  EXPECT_DOUBLE_EQ(gpu.half_tflops, 100);
  EXPECT_DOUBLE_EQ(gpu.tb_per_s, 2);
  EXPECT_DOUBLE_EQ(gpu.int8_tops, 200);  // custom: twice the 16-bit rate
  // INT8 on the tensor cores: 2 GFLOP at 200 TOP/s, 0.01 ms; H200's dense INT8 rate.
  EXPECT_NEAR(roofline_bound(2e9, 0, true, gpu, /*int8=*/true).compute_ms, 0.01, 1e-12);
  EXPECT_EQ(parse_gpu("h200").int8_tops, 1979);
  const RooflineBound tc = roofline_bound(2e9, 48e6, true, gpu);
  EXPECT_NEAR(tc.compute_ms, 0.02, 1e-12);
  EXPECT_NEAR(tc.memory_ms, 0.024, 1e-12);
  EXPECT_TRUE(tc.memory_bound());
  EXPECT_NEAR(tc.ms(), 0.024, 1e-12);
  const RooflineBound fp32 = roofline_bound(2e9, 48e6, false, gpu);
  EXPECT_NEAR(fp32.ms(), 0.2, 1e-12);
  EXPECT_FALSE(fp32.memory_bound());
  EXPECT_EQ(parse_gpu("H200").half_tflops, 989);
  // A graph's bound: a 16-bit convolution of 2 GFLOP reading and writing 1e6 bytes (compute:
  // 0.02 ms against 0.001), an FP32 op of 1 MFLOP reading and writing 4e6 bytes (memory: 0.004 ms
  // against 0.0001).
  Graph g;
  // As records: a BF16 1x1 convolution of 200 -> 400 channels on 50 x 50 pixels (0.4 GFLOP on the
  // tensor cores, 0.004 ms; its x 1e6 bytes, prepared weights 400 x 224 x 2 = 179,200, bias 1,600
  // and y 2e6: 0.00159 ms), its weight preparation (w 320,000 bytes read, 179,200 + 1,600
  // written: memory, 0.0002504 ms), and a raw FP32 node of 1 MFLOP reading and writing 4e6 bytes
  // (memory: 0.004 ms against 0.0001).
  const int x = g.tensor("x", {1, 200, 50, 50}, DType::BF16);      // 1e6 bytes
  const int w = g.tensor("w", {400, 200, 1, 1});
  const int w16 = g.tensor("w16", op::half16_conv_weights({400, 200, 1, 1}, false), DType::BF16);
  const int b16 = g.tensor("b16", {400});
  const int y = g.tensor("y", {1, 400, 50, 50}, DType::BF16);      // 2e6 bytes
  g.add(OpKind::PrepareConvWeights, "prep",
        PrepareConvWeightsArgs{.w = w, .prepared = w16, .prepared_bias = b16});
  GraphNode conv;
  conv.weight = {400, 200, 1, 1};
  const GraphNode& c = g.add(OpKind::PreparedConv2d, "conv",
                             PreparedConv2dArgs{.x = x, .prepared = w16, .prepared_bias = b16, .y = y}, conv);
  EXPECT_DOUBLE_EQ(c.flops, 2.0 * 400 * 200 * 2500);  // 0.4 GFLOP
  EXPECT_TRUE(on_matrix_units(g, c));
  EXPECT_EQ(op_label(g, c, Device::Cuda), "conv forward bf16 (tensor cores)");
  EXPECT_EQ(op_label(g, c, Device::Cpu), "conv forward bf16");
  const int b = g.tensor("b", {1000000});
  GraphNode relu;
  relu.op = OpKind::BatchNormRelu, relu.reads = {b}, relu.writes = {b}, relu.flops = 1e6;
  g.add(relu);
  const GraphBound whole = graph_bound(g, 0, gpu);
  EXPECT_NEAR(whole.compute_ms, 0.004, 1e-12);
  EXPECT_NEAR(whole.memory_ms, 0.004 + 0.0002504, 1e-12);
  EXPECT_NEAR(whole.ms(), 0.0082504, 1e-12);
  for (const char* bad :
       {"h300", "custom:1:2", "custom:1:2:x", "custom:1:-2:3", "custom:1:2:3:4"}) {
    try {
      parse_gpu(bad);
      ADD_FAILURE() << bad << " was accepted";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(std::string("--roofline ") + bad), std::string::npos)
          << e.what();
    }
  }
}

TEST(Graph, RefusesAPlannedTensorThatNoNodeTouches) {
  Graph g;
  g.tensor("orphan", {4});
  EXPECT_THROW(g.plan(), Error);
}

class GraphVariants
    : public ::testing::TestWithParam<std::tuple<OccupancyInput, bool, bool, int, bool>> {};

TEST_P(GraphVariants, NoTwoLiveTensorsShareBytes) {
  const auto [occupancy, transposed, grid_map, batch, training] = GetParam();
  const ModelConfig c = test::tiny_config(occupancy, transposed, grid_map);
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend);
  const test::TinyData data = test::tiny_data(c, batch, 7);
  net.forward(data.batch, training);
  const Graph& g = net.graph(training);
  ASSERT_GT(g.size(), 0u);
  const auto& ts = g.tensors();
  size_t inputs = 0;
  for (size_t i = 0; i < ts.size(); ++i) {
    if (ts[i].view_of >= 0) {
      const GraphTensor& base = ts[static_cast<size_t>(ts[i].view_of)];
      EXPECT_LE(ts[i].view_offset + ts[i].bytes(), base.bytes()) << ts[i].name;
    }
    if (!ts[i].planned()) continue;
    const auto [first_i, last_i] = g.lifetime(static_cast<int>(i));
    EXPECT_LE(ts[i].offset + ts[i].bytes(), g.planned_bytes()) << ts[i].name;
    if (ts[i].input) {
      ++inputs;
      EXPECT_EQ(first_i, -1) << ts[i].name;
    }
    for (size_t j = i + 1; j < ts.size(); ++j) {
      if (!ts[j].planned() || ts[j].bytes() == 0 || ts[i].bytes() == 0) continue;
      const auto [first_j, last_j] = g.lifetime(static_cast<int>(j));
      const bool meet = first_i <= last_j && first_j <= last_i;
      const bool overlap = ts[i].offset < ts[j].offset + ts[j].bytes() &&
                           ts[j].offset < ts[i].offset + ts[i].bytes();
      EXPECT_FALSE(meet && overlap)
          << ts[i].name << " [" << first_i << ", " << last_i << "] and " << ts[j].name << " ["
          << first_j << ", " << last_j << "] share bytes";
    }
  }
  // Pillar points and cells, the labels and loss coefficients, and each of the occupancy and
  // grid-map inputs the variant has.
  const size_t expected_inputs =
      4 + (occupancy != OccupancyInput::None ? 1 : 0) + (grid_map ? 1 : 0);
  EXPECT_EQ(inputs, expected_inputs);
  EXPECT_NE(net.memory_report(training).find("planned tensors"), std::string::npos);
}

INSTANTIATE_TEST_SUITE_P(Tiny, GraphVariants,
                         ::testing::Combine(::testing::Values(OccupancyInput::None,
                                                              OccupancyInput::Observability2D,
                                                              OccupancyInput::Occupancy3D),
                                            ::testing::Bool(), ::testing::Bool(),
                                            ::testing::Values(1, 2), ::testing::Bool()));

// Parameters 0, 1, 3 trainable at offsets 0, 10, 30 of a 40-element gradient array (2 is a
// buffer). Node 0 writes parameter 3's gradient, node 1 parameter 1's, node 2 parameter 0's,
// node 3 parameter 3's again. From the end of the array: buckets of at least 10 elements are
// [30, 40) (last written by node 3), [10, 30) (node 1), [0, 10) (node 2), handed out in the
// order they are ready; of at least 25: [10, 40) (node 3) and what is left, [0, 10) (node 2).
TEST(Graph, GradientBucketsAreReadyAfterTheLastWriteOfTheirParameters) {
  Graph g;
  const int g0 = g.parameter(0, {10}, true), g1 = g.parameter(1, {20}, true);
  const int g3 = g.parameter(3, {10}, true), w3 = g.parameter(3, {10}, false);
  g.add(node({w3}, {g3}));
  g.add(node({w3}, {g1}));
  g.add(node({w3}, {g0}));
  g.add(node({w3}, {g3}));
  const std::vector<int64_t> offsets = {0, 10, -1, 30};
  const auto expect = [](const std::vector<GradientBucket>& b,
                         const std::vector<std::tuple<size_t, int64_t, int64_t>>& want) {
    ASSERT_EQ(b.size(), want.size());
    for (size_t i = 0; i < b.size(); ++i) {
      EXPECT_EQ(b[i].after, std::get<0>(want[i])) << "bucket " << i;
      EXPECT_EQ(b[i].offset, std::get<1>(want[i])) << "bucket " << i;
      EXPECT_EQ(b[i].count, std::get<2>(want[i])) << "bucket " << i;
    }
  };
  expect(g.gradient_buckets(offsets, 40, 10), {{1, 10, 20}, {2, 0, 10}, {3, 30, 10}});
  expect(g.gradient_buckets(offsets, 40, 25), {{2, 0, 10}, {3, 10, 30}});
  expect(g.gradient_buckets(offsets, 40, 0), {{3, 0, 40}});
  // A trainable parameter whose gradient no node writes.
  EXPECT_THROW(g.gradient_buckets({0, 10, 20, 30}, 40, 10), Error);
}

// Records each bucket's gradients when the backward hands it out.
class BucketRecorder final : public PillarSegNet::GradientListener {
 public:
  explicit BucketRecorder(const Ref& grads) : grads_(grads) {}
  void bucket_ready(int64_t offset, int64_t count) override {
    buckets.push_back({offset, count});
    copies.emplace_back(grads_.data + offset, grads_.data + offset + count);
  }
  void between_nodes() override { ++nodes; }
  std::vector<std::pair<int64_t, int64_t>> buckets;
  std::vector<std::vector<float>> copies;
  int nodes = 0;

 private:
  Ref grads_;
};

// On every variant of the tiny model: the buckets (of at least 64 elements) cover the gradient
// array once, and each bucket's gradients when it is handed out are already the final ones (no
// later node writes them; the CPU backend computes each node before returning: after a backward
// without a listener and the gradients zeroed, a bucket handed out early holds zeros); the
// gradients are those of a backward without a listener, bit for bit.
class TrainingGraphVariants : public GraphVariants {};

TEST_P(TrainingGraphVariants, BackwardHandsOutEachGradientBucketFinished) {
  const auto [occupancy, transposed, grid_map, batch, training] = GetParam();
  ASSERT_TRUE(training);
  const ModelConfig c = test::tiny_config(occupancy, transposed, grid_map);
  auto backend = make_cpu_backend();
  PillarSegNet net(c, *backend);
  const test::TinyData data = test::tiny_data(c, batch, 7);
  const auto step = [&](PillarSegNet::GradientListener* listener) {
    net.forward(data.batch, true);
    net.loss(data.labels, LossKind::CrossEntropy, test::kCoefficients);
    net.backward(listener, 64);
    return net.parameters().download_flat(net.parameters().grads());
  };
  const std::vector<float> plain = step(nullptr);
  // Zeros, so that a bucket handed out before its last write shows (the same step again would
  // otherwise leave the same gradients there).
  net.parameters().zero_grads();
  BucketRecorder recorder(net.parameters().grads());
  const std::vector<float> grads = step(&recorder);
  EXPECT_EQ(std::memcmp(plain.data(), grads.data(), plain.size() * sizeof(float)), 0);
  ASSERT_GT(recorder.buckets.size(), 3u);
  EXPECT_EQ(recorder.buckets.size(), net.gradient_buckets(64).size());
  EXPECT_GT(recorder.nodes, static_cast<int>(recorder.buckets.size()));
  std::vector<int> covered(static_cast<size_t>(net.parameters().num_trainable()), 0);
  for (size_t b = 0; b < recorder.buckets.size(); ++b) {
    const auto [offset, count] = recorder.buckets[b];
    for (int64_t i = offset; i < offset + count; ++i) {
      ++covered[static_cast<size_t>(i)];
      ASSERT_EQ(recorder.copies[b][static_cast<size_t>(i - offset)], grads[static_cast<size_t>(i)])
          << "bucket [" << offset << ", " << offset + count << ") changed after it was handed out";
    }
  }
  for (size_t i = 0; i < covered.size(); ++i) ASSERT_EQ(covered[i], 1) << "gradient element " << i;
}

INSTANTIATE_TEST_SUITE_P(Tiny, TrainingGraphVariants,
                         ::testing::Combine(::testing::Values(OccupancyInput::None,
                                                              OccupancyInput::Observability2D,
                                                              OccupancyInput::Occupancy3D),
                                            ::testing::Bool(), ::testing::Bool(),
                                            ::testing::Values(1, 2), ::testing::Values(true)));
