// The op graph and its lifetime planner (engine/model/graph.hpp): a hand-built graph's offsets
// and block size, and on every variant of the tiny model, for eval and training at batch 1 and
// 2, the planner's invariant: two tensors alive at the same node never share a byte, inputs
// are alive from the start, outputs to the end, and views lie inside their tensor.
#include <gtest/gtest.h>

#include <climits>
#include <tuple>

#include "core/error.hpp"
#include "engine/model/graph.hpp"
#include "engine/model/pillarsegnet.hpp"
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
