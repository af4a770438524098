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
  const int h = g.tensor("h", {5}, DType::U16);          // 10
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
  const int canvas = g.tensor("canvas", {1000}, DType::U16);
  const int cells = g.tensor("cells", {100, 3}, DType::I32);
  g.at(cells).dynamic_rows = true;
  GraphNode copy = node({x, canvas}, {canvas});
  copy.op = OpKind::CopyChannelsHalf;
  copy.args = {x, canvas};
  g.add(copy);
  GraphNode scatter = node({rows, cells, canvas}, {canvas});
  scatter.op = OpKind::Scatter;
  scatter.args = {rows, cells, canvas};
  g.add(scatter);
  EXPECT_EQ(g.node_bytes(3, 7), 36u);
  EXPECT_EQ(g.node_bytes(4, 7), 308u);
}

// The roofline bound (engine/model/roofline.hpp) by hand: 2 GFLOP and 48 MB on custom peaks of
// 10 TFLOP/s FP32, 100 TFLOP/s 16-bit and 2 TB/s: on the tensor cores compute 0.02 ms < memory
// 0.024 ms (memory-bound); on the CUDA cores compute 0.2 ms (compute-bound).
TEST(Roofline, BoundsAnOpByItsFlopsAndBytes) {
  const GpuPeaks gpu = parse_gpu("custom:10:100:2");
  EXPECT_DOUBLE_EQ(gpu.fp32_tflops, 10);
  EXPECT_DOUBLE_EQ(gpu.half_tflops, 100);
  EXPECT_DOUBLE_EQ(gpu.tb_per_s, 2);
  const RooflineBound tc = roofline_bound(2e9, 48e6, true, gpu);
  EXPECT_NEAR(tc.compute_ms, 0.02, 1e-12);
  EXPECT_NEAR(tc.memory_ms, 0.024, 1e-12);
  EXPECT_TRUE(tc.memory_bound());
  EXPECT_NEAR(tc.ms(), 0.024, 1e-12);
  const RooflineBound fp32 = roofline_bound(2e9, 48e6, false, gpu);
  EXPECT_NEAR(fp32.ms(), 0.2, 1e-12);
  EXPECT_FALSE(fp32.memory_bound());
  EXPECT_EQ(parse_gpu("H200").half_tflops, 989);
  EXPECT_TRUE(runs_on_tensor_cores(op_name(OpKind::Conv2dHalf)));
  EXPECT_TRUE(runs_on_tensor_cores(op_name(OpKind::ConvTranspose2x2BackwardHalf)));
  EXPECT_FALSE(runs_on_tensor_cores(op_name(OpKind::Conv2d)));
  EXPECT_FALSE(runs_on_tensor_cores(op_name(OpKind::PfnForward)));
  // A graph's bound: a 16-bit convolution of 2 GFLOP reading and writing 1e6 bytes (compute:
  // 0.02 ms against 0.001), an FP32 op of 1 MFLOP reading and writing 4e6 bytes (memory: 0.004 ms
  // against 0.0001).
  Graph g;
  const int a = g.tensor("a", {250000, 2}, DType::U16), b = g.tensor("b", {1000000});
  GraphNode conv;
  conv.op = OpKind::Conv2dHalf, conv.reads = {a}, conv.writes = {a}, conv.flops = 2e9;
  g.add(conv);
  GraphNode relu;
  relu.op = OpKind::BatchNormRelu, relu.reads = {b}, relu.writes = {b}, relu.flops = 1e6;
  g.add(relu);
  const GraphBound whole = graph_bound(g, 0, gpu);
  EXPECT_NEAR(whole.compute_ms, 0.02, 1e-12);
  EXPECT_NEAR(whole.memory_ms, 0.004, 1e-12);
  EXPECT_NEAR(whole.ms(), 0.024, 1e-12);
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
