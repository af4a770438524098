// The input pipeline and the segmenter (engine/pipeline/) on the CUDA backend (the emulation here;
// as test_pipeline_gpu, a GPU) against the CPU backend: the same pillars, slots and order, the same
// input maps and the same labels from raw points, at odd grids, with the paper's pillar cap, with
// points outside the grid and non-finite ones, and on the real SemanticKITTI scan at a reduced
// grid; the recorded graph against the same work run directly; no allocation in the steady state,
// and the bytes that cross the bus per scan.
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "core/error.hpp"
#include "core/grid.hpp"
#include "core/point.hpp"
#include "engine/backend/backend.hpp"
#include "engine/cuda/cuda_backend.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/model/calibration.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/pipeline/scan_pipeline.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "tests/support/scans.hpp"
#include "tests/support/test_support.hpp"
#include "tests/support/tiny_model.hpp"

using namespace pillarseg;

namespace {

#if defined(PILLARSEG_CUDA_EMULATION)
constexpr std::int64_t kMapUlps = 0;  // the emulation uses the host's log1p and exp
#else
constexpr std::int64_t kMapUlps = 1;  // a GPU's double log1p and exp are within an ulp
#endif

struct Variant {
  const char* name;
  OccupancyInput occupancy;
  bool pillars, grid_map, transposed;
  int max_pillars;
};

const Variant kVariants[] = {
    {"pillars", OccupancyInput::None, true, false, false, 0},
    {"pillars_2d", OccupancyInput::Observability2D, true, false, true, 0},
    {"pillars_3d", OccupancyInput::Occupancy3D, true, false, false, 0},
    {"grid_map", OccupancyInput::None, false, true, false, 0},
    {"pillars_2d_grid_map_capped", OccupancyInput::Observability2D, true, true, false, 40},
};

// The tiny model on an odd grid: 27 x 19 cells of 0.25 m, z in [-1, 1) in 4 layers.
ModelConfig pipeline_config(const Variant& v) {
  ModelConfig c = test::tiny_config(v.occupancy, v.transposed, v.grid_map);
  c.grid.x_min = -3.0, c.grid.x_max = -3.0 + 27 * 0.25;
  c.grid.y_min = -2.25, c.grid.y_max = -2.25 + 19 * 0.25;
  c.grid.cell = 0.25;
  c.pillar_input = v.pillars;
  c.max_pillars = v.max_pillars;
  return c;
}

// (An absent input stream is a Ref without data.)
template <class T>
std::vector<T> download(Backend& backend, const RefT<T>& r) {
  if (r.data == nullptr) return {};
  std::vector<T> host(static_cast<size_t>(r.numel()));
  if (!host.empty()) backend.download(host.data(), r.data, r.bytes());
  return host;
}

// Float vectors within `ulps` (exact when 0), naming the first element that is not.
::testing::AssertionResult within_ulps(const std::vector<float>& actual,
                                       const std::vector<float>& expected, std::int64_t ulps) {
  if (actual.size() != expected.size())
    return ::testing::AssertionFailure() << "size " << actual.size() << " != " << expected.size();
  for (size_t i = 0; i < actual.size(); ++i) {
    const std::int64_t a = std::bit_cast<std::int32_t>(actual[i]);
    const std::int64_t e = std::bit_cast<std::int32_t>(expected[i]);
    if (std::abs(a - e) > ulps)
      return ::testing::AssertionFailure()
             << "element " << i << ": " << actual[i] << " != expected " << expected[i];
  }
  return ::testing::AssertionSuccess();
}

// What a pipeline produced for one scan, on the host.
struct PreparedInputs {
  int64_t rows = 0, pillars = 0;  // rows planned, P' (num_pillars)
  std::vector<float> pillar_points, occupancy, grid_map;
  std::vector<int32_t> pillar_cells;
};

// Runs the pipeline on `points` for one sample; recorded: the capacity-shaped work of a graph
// (NaN padding, gather over the whole buffer).
PreparedInputs run_pipeline(const ModelConfig& c, Backend& backend, const std::vector<Point>& points,
                            bool recorded) {
  PillarSegNet net(c, backend, 3);
  ScanPipeline pipeline(c, backend);
  Ref loaded = pipeline.load_points(points);
  if (recorded) {
    pipeline.pad_points();
    loaded = pipeline.point_buffer();
  }
  PreparedInputs out;
  out.rows = pipeline.gather_pillars(loaded);
  const PillarSegNet::Inputs in = net.prepare(1, out.rows, false);
  pipeline.fill_pillars(loaded, out.rows, 0, 0, in);
  pipeline.fill_maps(loaded, Eigen::Vector3d(0.3, -0.1, 0.0), 0, in);
  out.pillars = c.pillar_input ? download(backend, pipeline.gathered_pillars())[0] : 0;
  out.pillar_points = download(backend, in.pillar_points);
  out.pillar_cells = download(backend, in.pillar_cells);
  out.occupancy = download(backend, in.occupancy);
  out.grid_map = download(backend, in.grid_map);
  return out;
}

}  // namespace

class PipelineVariant : public ::testing::TestWithParam<Variant> {};

TEST_P(PipelineVariant, DeviceInputsEqualTheCpuBackend) {
  const ModelConfig c = pipeline_config(GetParam());
  std::uint64_t seed = 300;
  for (const std::int64_t m : {0, 1, 700, 2600}) {
    SCOPED_TRACE(::testing::Message() << m << " points");
    const std::vector<Point> points = test::random_scan(m, c.grid, seed++);
    auto cpu = make_cpu_backend();
    const PreparedInputs expected = run_pipeline(c, *cpu, points, false);
    EXPECT_EQ(expected.rows, expected.pillars) << "the CPU backend reads exactly P' rows";
    for (const bool recorded : {false, true}) {
      SCOPED_TRACE(recorded ? "recorded (padded to the capacity)" : "direct");
      CudaBackend cuda;
      const PreparedInputs got = run_pipeline(c, cuda, points, recorded);
      ASSERT_EQ(got.pillars, expected.pillars);
      ASSERT_GE(got.rows, got.pillars);
      // The first P' rows: the CPU's, bit for bit; the rows after: no cell (their points are
      // left unwritten: the decoration stops at the device's P', ScanPipeline::live_pillar_rows).
      const auto P = static_cast<size_t>(expected.pillars);
      const size_t row_floats = static_cast<size_t>(c.max_points_per_pillar) * 10;
      const std::vector<float> head(got.pillar_points.begin(),
                                    got.pillar_points.begin() + static_cast<std::ptrdiff_t>(P * row_floats));
      EXPECT_EQ(head, expected.pillar_points);
      const std::vector<int32_t> cells(got.pillar_cells.begin(),
                                       got.pillar_cells.begin() + static_cast<std::ptrdiff_t>(3 * P));
      EXPECT_EQ(cells, expected.pillar_cells);
      for (size_t i = 3 * P; i < got.pillar_cells.size(); ++i) ASSERT_EQ(got.pillar_cells[i], -1) << i;
      EXPECT_TRUE(within_ulps(got.occupancy, expected.occupancy, kMapUlps));
      EXPECT_TRUE(within_ulps(got.grid_map, expected.grid_map, kMapUlps));
    }
  }
}

INSTANTIATE_TEST_SUITE_P(Variants, PipelineVariant, ::testing::ValuesIn(kVariants),
                         [](const ::testing::TestParamInfo<Variant>& case_info) { return std::string(case_info.param.name); });

namespace {

// Labels (H W) and probabilities (12 H W) of one scan.
struct Segmented {
  std::vector<uint8_t> labels;
  std::vector<float> probabilities;
};

Segmented segment(ScanSegmenter& segmenter, const std::vector<Point>& points, bool probabilities = true) {
  const auto cells = static_cast<size_t>(segmenter.model().grid.cells());
  Segmented s{std::vector<uint8_t>(cells), std::vector<float>(probabilities ? 12 * cells : 0)};
  segmenter.segment(points, s.labels.data(), probabilities ? s.probabilities.data() : nullptr);
  return s;
}

// Labels agree wherever the expected probabilities' top two are apart by more than `gap`; at
// least 90% of the cells are decided so.
void expect_same_decided_labels(const Segmented& got, const Segmented& expected, double gap) {
  const size_t cells = expected.labels.size();
  size_t decided = 0;
  for (size_t i = 0; i < cells; ++i) {
    std::vector<float> p(12);
    for (size_t k = 0; k < 12; ++k) p[k] = expected.probabilities[k * cells + i];
    std::sort(p.begin(), p.end(), std::greater<>());
    if (p[0] - p[1] <= gap && expected.labels[i] != 0) continue;
    ++decided;
    ASSERT_EQ(+got.labels[i], +expected.labels[i]) << "cell " << i;
  }
  EXPECT_GE(decided, cells * 9 / 10);
}

std::unique_ptr<ScanSegmenter> cpu_segmenter(const ModelConfig& c, bool mask) {
  SegmenterOptions o;
  o.mask_unobserved = mask;
  return std::make_unique<ScanSegmenter>(c, make_cpu_reference_backend(), o, /*seed=*/7);
}

std::unique_ptr<ScanSegmenter> cuda_segmenter(const ModelConfig& c, bool mask, bool graphs = true,
                                              Precision precision = Precision::F32) {
  SegmenterOptions o;
  o.mask_unobserved = mask;
  o.precision = precision;
  CudaBackendOptions options;
  options.graphs = graphs;
  return std::make_unique<ScanSegmenter>(c, std::make_unique<CudaBackend>(options), o, /*seed=*/7);
}

}  // namespace

TEST_P(PipelineVariant, SegmenterLabelsEqualTheCpuBackend) {
  const ModelConfig c = pipeline_config(GetParam());
  for (const bool mask : {false, true}) {
    SCOPED_TRACE(mask ? "masking unobserved cells" : "every cell");
    auto cpu = cpu_segmenter(c, mask);
    auto cuda = cuda_segmenter(c, mask);
    std::uint64_t seed = 400;
    for (const std::int64_t m : {2000, 900, 0}) {
      SCOPED_TRACE(::testing::Message() << m << " points");
      const std::vector<Point> points = test::random_scan(m, c.grid, seed++);
      const Segmented expected = segment(*cpu, points), got = segment(*cuda, points);
      EXPECT_TRUE(test::all_close(got.probabilities.data(), expected.probabilities.data(),
                                  static_cast<int64_t>(got.probabilities.size()), 1e-6, 2e-5));
      expect_same_decided_labels(got, expected, 1e-4);
      if (mask && m == 0) {
        // Nothing observed: every cell unlabeled, every probability 0.
        EXPECT_TRUE(std::all_of(got.labels.begin(), got.labels.end(), [](uint8_t k) { return k == 0; }));
        EXPECT_TRUE(std::all_of(got.probabilities.begin(), got.probabilities.end(), [](float p) { return p == 0; }));
      }
    }
  }
}

TEST(Segmenter, RecordedGraphEqualsTheDirectRunBitForBit) {
  const ModelConfig c = pipeline_config(kVariants[1]);  // pillars + 2D occupancy, transposed
  auto graphed = cuda_segmenter(c, true, /*graphs=*/true);
  auto direct = cuda_segmenter(c, true, /*graphs=*/false);
  std::uint64_t seed = 500;
  // Growing (re-recorded at a larger capacity), shrinking (the same recording), empty, labels
  // alone and with probabilities (a recording each).
  for (const auto& [m, probabilities] : std::vector<std::pair<std::int64_t, bool>>{
           {500, true}, {500, false}, {6000, true}, {300, true}, {0, false}, {5000, false}}) {
    SCOPED_TRACE(::testing::Message() << m << " points" << (probabilities ? ", probabilities" : ""));
    const std::vector<Point> points = test::random_scan(m, c.grid, seed++);
    const Segmented a = segment(*graphed, points, probabilities), b = segment(*direct, points, probabilities);
    EXPECT_EQ(a.labels, b.labels);
    EXPECT_EQ(a.probabilities, b.probabilities);
  }
  const Backend::Counters counters = graphed->backend().counters();
  // Recorded: probabilities and labels at the first capacity, probabilities at the second (6000
  // points), labels at the second (the empty scan); replayed: the scans of 300 and 5000 points.
  EXPECT_EQ(counters.graphs_captured, 4);
  EXPECT_EQ(counters.graph_replays, 2);
  EXPECT_EQ(direct->backend().counters().graphs_captured, 0);
}

// The 16-bit weights are prepared outside the recorded graph, once: after the weights change,
// the replayed recording runs on weights prepared again (the same result as a segmenter that
// records nothing).
TEST(Segmenter, ReplayedBf16FollowsChangedWeights) {
  const ModelConfig c = pipeline_config(kVariants[0]);
  auto graphed = cuda_segmenter(c, false, /*graphs=*/true, Precision::BF16);
  auto direct = cuda_segmenter(c, false, /*graphs=*/false, Precision::BF16);
  const std::vector<Point> points = test::random_scan(1500, c.grid, 700);
  const Segmented before = segment(*graphed, points);  // records
  EXPECT_EQ(segment(*graphed, points).probabilities, before.probabilities);  // replays
  EXPECT_EQ(segment(*direct, points).probabilities, before.probabilities);
  for (ScanSegmenter* s : {graphed.get(), direct.get()}) {
    ParameterSet& ps = s->net().parameters();
    const int conv = ps.find("segmentation_head.up1.conv.double_conv.3.weight");
    ASSERT_GE(conv, 0);
    Tensor<float> w = ps.download(conv);
    for (int64_t i = 0; i < w.numel(); ++i) w.data()[i] = -w.data()[i];
    ps.upload(conv, w);
  }
  const Segmented after = segment(*graphed, points);  // replays
  EXPECT_EQ(graphed->backend().counters().graph_replays, 2);
  EXPECT_NE(after.probabilities, before.probabilities);
  EXPECT_EQ(after.probabilities, segment(*direct, points).probabilities);
}

TEST(Segmenter, SteadyStateAllocatesNothingAndMovesOnlyPointsAndLabels) {
  const ModelConfig c = pipeline_config(kVariants[4]);  // every input stream
  auto segmenter = cuda_segmenter(c, true);
  Backend& backend = segmenter->backend();
  segment(*segmenter, test::random_scan(3000, c.grid, 600), false);  // plans and records
  const Backend::Counters warm = backend.counters();
  std::uint64_t seed = 601;
  for (const std::int64_t m : {2999, 1, 2500, 0, 3000}) {
    const Backend::Counters before = backend.counters();
    segment(*segmenter, test::random_scan(m, c.grid, seed++), false);
    const Backend::Counters after = backend.counters();
    EXPECT_EQ(after.bytes_uploaded - before.bytes_uploaded, 16 * m + 4) << m << " points + their count";
    EXPECT_EQ(after.bytes_downloaded - before.bytes_downloaded, c.grid.cells()) << "H x W labels";
  }
  const Backend::Counters steady = backend.counters();
  EXPECT_EQ(steady.allocations, warm.allocations);
  EXPECT_EQ(steady.graphs_captured, warm.graphs_captured);
  EXPECT_EQ(steady.graph_replays, warm.graph_replays + 5);
}

// INT8 calibration through a segmenter on a backend that records its pipeline (what bench
// --precision int8 does without stored scales): while the calibration observes, the passes run
// unrecorded (it downloads each convolution's input as the forward runs), and give the CPU's
// scales; afterwards the recording replays again.
TEST(Segmenter, CalibratesOnABackendThatRecords) {
  const ModelConfig c = pipeline_config(kVariants[0]);
  auto cpu = cpu_segmenter(c, false);
  auto cuda = cuda_segmenter(c, false);
  const std::vector<Point> points = test::random_scan(2500, c.grid, 940);
  segment(*cuda, points, false);  // records the pipeline
  const auto calibrate = [&](ScanSegmenter& segmenter) {
    InputScaleCalibrator calibrator;
    const CalibrationScope observing(segmenter.net(), calibrator);
    segment(segmenter, points, false);
    return calibrator.inputs();
  };
  const Backend::Counters before = cuda->backend().counters();
  const std::map<std::string, Int8Input> expected = calibrate(*cpu), got = calibrate(*cuda);
  EXPECT_EQ(cuda->backend().counters().graph_replays, before.graph_replays);
  ASSERT_EQ(got.size(), expected.size());
  ASSERT_GT(got.size(), 0u);
  for (const auto& [key, input] : expected) {
    ASSERT_TRUE(got.contains(key)) << key;
    EXPECT_NEAR(got.at(key).scale, input.scale, 1e-4 * input.scale) << key;
    EXPECT_EQ(got.at(key).non_negative, input.non_negative) << key;
  }
  segment(*cuda, points, false);
  EXPECT_EQ(cuda->backend().counters().graph_replays, before.graph_replays + 1);
}

TEST(Segmenter, RealScanAtAReducedGridMatchesTheCpuBackend) {
  const std::filesystem::path bin =
      test::shared_data_dir() / "semantickitti/sequences/99/velodyne/000000.bin";
  if (!std::filesystem::exists(bin)) GTEST_SKIP() << "no real scan at " << bin;
  const Scan scan = read_scan(bin);
  ModelConfig c = test::tiny_config(OccupancyInput::Observability2D, false, false);
  c.grid = GridSpec{};  // the paper's area and z range ...
  c.grid.cell = 1.0;    // ... at 1 m: 100 x 50 cells
  c.max_points_per_pillar = 20;
  c.depth = 3;
  auto cpu = cpu_segmenter(c, true);
  auto cuda = cuda_segmenter(c, true);
  const Segmented expected = segment(*cpu, scan.points), got = segment(*cuda, scan.points);
  EXPECT_TRUE(test::all_close(got.probabilities.data(), expected.probabilities.data(),
                              static_cast<int64_t>(got.probabilities.size()), 1e-6, 2e-5));
  expect_same_decided_labels(got, expected, 1e-4);
  // The inputs behind them: every pillar of the scan, bit for bit.
  auto cpu_backend = make_cpu_backend();
  CudaBackend cuda_backend;
  const PreparedInputs a = run_pipeline(c, *cpu_backend, scan.points, false);
  const PreparedInputs b = run_pipeline(c, cuda_backend, scan.points, true);
  EXPECT_GT(a.pillars, 2000);
  ASSERT_EQ(b.pillars, a.pillars);
  EXPECT_TRUE(std::equal(a.pillar_points.begin(), a.pillar_points.end(), b.pillar_points.begin()));
  EXPECT_TRUE(std::equal(a.pillar_cells.begin(), a.pillar_cells.end(), b.pillar_cells.begin()));
  EXPECT_TRUE(within_ulps(b.occupancy, a.occupancy, kMapUlps));
}

TEST(Segmenter, ErrorsSayWhatIsWrong) {
  const ModelConfig c = pipeline_config(kVariants[0]);
  auto segmenter = cpu_segmenter(c, false);
  const std::vector<Point> points = test::random_scan(10, c.grid, 700);
  try {
    segmenter->segment(points, nullptr);
    FAIL() << "no labels buffer";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("labels must point to H x W = 513 bytes"), std::string::npos) << e.what();
  }
}

namespace {

// The tiny model with 2D occupancy on a grid symmetric about the sensor: 27 x 19 cells of 0.25 m.
ModelConfig symmetric_config() {
  ModelConfig c = pipeline_config(kVariants[1]);
  c.grid.x_min = -3.375, c.grid.x_max = 3.375;
  c.grid.y_min = -2.375, c.grid.y_max = 2.375;
  return c;
}

std::unique_ptr<ScanSegmenter> flipping_segmenter(const ModelConfig& c, std::unique_ptr<Backend> backend, int flips,
                                                  bool mask) {
  SegmenterOptions o;
  o.flips = flips;
  o.mask_unobserved = mask;
  return std::make_unique<ScanSegmenter>(c, std::move(backend), o, /*seed=*/7);
}

// The points mirrored: y -> -y where bit 0 of `copy` is set, x -> -x where bit 1 is.
std::vector<Point> mirrored(std::vector<Point> points, int copy) {
  for (Point& p : points) {
    if (copy & 1) p.y = -p.y;
    if (copy & 2) p.x = -p.x;
  }
  return points;
}

// Probabilities (12 H W) mirrored in the same way, cell (iy, ix) from (H - 1 - iy, ix) etc.
std::vector<float> mirrored(const std::vector<float>& probs, const GridSpec& grid, int copy) {
  const int64_t w = grid.width(), h = grid.height();
  std::vector<float> out(probs.size());
  for (int64_t k = 0; k < 12; ++k)
    for (int64_t iy = 0; iy < h; ++iy)
      for (int64_t ix = 0; ix < w; ++ix)
        out[static_cast<size_t>((k * h + iy) * w + ix)] = probs[static_cast<size_t>(
            (k * h + ((copy & 1) ? h - 1 - iy : iy)) * w + ((copy & 2) ? w - 1 - ix : ix))];
  return out;
}

}  // namespace

// flips 2 and 4: the softmax is the mean of the one-pass segmenter's on the mirrored copies,
// mirrored back (summed in the copies' order, then scaled: bit for bit), the labels its arg-max,
// 0 where every copy masked the cell; and the segmenter then commutes with the mirrors.
TEST(Segmenter, FlipsAverageTheMirroredCopies) {
  const ModelConfig c = symmetric_config();
  const int64_t cells = c.grid.cells();
  for (const bool mask : {false, true}) {
    SCOPED_TRACE(mask ? "masking unobserved cells" : "every cell");
    auto single = flipping_segmenter(c, make_cpu_reference_backend(), 1, mask);
    // (With masking, few points: cells no ray of any copy reaches.)
    const std::vector<Point> points = test::random_scan(mask ? 60 : 1500, c.grid, 910);
    for (const int flips : {2, 4}) {
      SCOPED_TRACE(::testing::Message() << flips << " flips");
      auto flipping = flipping_segmenter(c, make_cpu_reference_backend(), flips, mask);
      std::vector<float> sum(static_cast<size_t>(12 * cells), 0.0f);
      for (int copy = 0; copy < flips; ++copy) {
        const std::vector<float> p = mirrored(segment(*single, mirrored(points, copy)).probabilities, c.grid, copy);
        for (size_t i = 0; i < sum.size(); ++i) sum[i] += p[i];
      }
      Segmented expected{std::vector<uint8_t>(static_cast<size_t>(cells), 0), sum};
      for (float& v : expected.probabilities) v *= 1.0f / static_cast<float>(flips);
      int64_t unobserved = 0;
      for (int64_t i = 0; i < cells; ++i) {
        float best = 0.0f;
        for (int64_t k = 0; k < 12; ++k) {
          const float v = sum[static_cast<size_t>(k * cells + i)];
          if (v > best) best = v, expected.labels[static_cast<size_t>(i)] = static_cast<uint8_t>(k + 1);
        }
        unobserved += expected.labels[static_cast<size_t>(i)] == 0;
      }
      EXPECT_EQ(unobserved > 0, mask);
      const Segmented got = segment(*flipping, points);
      EXPECT_EQ(got.probabilities, expected.probabilities);
      EXPECT_EQ(got.labels, expected.labels);
      const Segmented one = segment(*single, points);
      EXPECT_NE(got.probabilities, one.probabilities) << "the mirrored copies must change the result";
      // Labels alone: the same map.
      EXPECT_EQ(segment(*flipping, points, false).labels, got.labels);
      // Commuting with the mirrors: the copies of a mirrored scan are the scan's copies, in
      // another order (so within rounding).
      for (int copy = 1; copy < flips; ++copy) {
        SCOPED_TRACE(::testing::Message() << "scan mirrored as copy " << copy);
        const Segmented m = segment(*flipping, mirrored(points, copy));
        const std::vector<float> back = mirrored(m.probabilities, c.grid, copy);
        EXPECT_TRUE(test::all_close(back.data(), got.probabilities.data(), static_cast<int64_t>(back.size()), 1e-6,
                                    1e-6));
      }
    }
  }
}

// The CUDA backend's segmenter (its recorded graph with the probabilities) flips as the CPU's.
TEST(Segmenter, FlipsOnTheCudaBackendEqualTheCpuBackend) {
  const ModelConfig c = symmetric_config();
  auto cpu = flipping_segmenter(c, make_cpu_reference_backend(), 4, true);
  CudaBackendOptions options;
  auto cuda = flipping_segmenter(c, std::make_unique<CudaBackend>(options), 4, true);
  std::uint64_t seed = 920;
  for (const std::int64_t m : {1200, 800}) {
    const std::vector<Point> points = test::random_scan(m, c.grid, seed++);
    const Segmented expected = segment(*cpu, points), got = segment(*cuda, points);
    EXPECT_TRUE(test::all_close(got.probabilities.data(), expected.probabilities.data(),
                                static_cast<int64_t>(got.probabilities.size()), 1e-6, 2e-5));
    expect_same_decided_labels(got, expected, 1e-4);
  }
}

// On a GPU the copies' probabilities are summed where they are (Backend::mirror_add): after the
// first scan, each scan's four passes replay the recorded graph, upload the copies' points and
// bring down only the result, the H x W labels (and 12 x H x W probabilities where asked).
TEST(Segmenter, FlipsOnTheDeviceMoveOnlyPointsAndTheResult) {
  const ModelConfig c = symmetric_config();
  CudaBackendOptions options;
  auto segmenter = flipping_segmenter(c, std::make_unique<CudaBackend>(options), 4, true);
  Backend& backend = segmenter->backend();
  segment(*segmenter, test::random_scan(1500, c.grid, 930), false);  // plans, records
  segment(*segmenter, test::random_scan(1500, c.grid, 931), true);   // the same with probabilities
  const Backend::Counters warm = backend.counters();
  std::uint64_t seed = 932;
  const int64_t cells = c.grid.cells();
  for (const auto& [m, probabilities] :
       std::vector<std::pair<std::int64_t, bool>>{{1400, false}, {900, true}, {0, false}}) {
    const Backend::Counters before = backend.counters();
    segment(*segmenter, test::random_scan(m, c.grid, seed++), probabilities);
    const Backend::Counters after = backend.counters();
    EXPECT_EQ(after.bytes_uploaded - before.bytes_uploaded, 4 * (16 * m + 4)) << "4 copies of " << m << " points";
    EXPECT_EQ(after.bytes_downloaded - before.bytes_downloaded, cells + (probabilities ? 12 * 4 * cells : 0))
        << m << " points, probabilities " << probabilities;
    EXPECT_EQ(after.graph_replays - before.graph_replays, 4);
  }
  EXPECT_EQ(backend.counters().allocations, warm.allocations);
  EXPECT_EQ(backend.counters().graphs_captured, warm.graphs_captured);
}

TEST(Segmenter, FlipsNeedAGridSymmetricAboutTheSensor) {
  const auto message = [](const ModelConfig& c, int flips) {
    try {
      flipping_segmenter(c, make_cpu_reference_backend(), flips, false);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  const ModelConfig odd = pipeline_config(kVariants[0]);  // x [-3, 3.75], y [-2.25, 2.5]
  EXPECT_NE(message(odd, 2).find("flips 2: the mirror y -> -y maps the grid onto itself only when it is symmetric "
                                 "about the sensor; grid.y is [-2.25, 2.5]"),
            std::string::npos)
      << message(odd, 2);
  ModelConfig half = symmetric_config();
  half.grid.x_min = 0.0, half.grid.x_max = 6.75;
  EXPECT_EQ(message(half, 2), "");
  EXPECT_NE(message(half, 4).find("grid.x is [0, 6.75]"), std::string::npos) << message(half, 4);
  EXPECT_NE(message(symmetric_config(), 3).find("flips: 3 mirrored copies"), std::string::npos);
  EXPECT_EQ(message(odd, 1), "");
}

