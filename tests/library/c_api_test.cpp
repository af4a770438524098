// The C API (include/pillarseg/pillarseg.h) through the shared library, as a C program or a
// Python ctypes user calls it: the same labels and probabilities as the engine's segmenter; every
// bad argument and bad file an error message in the caller's buffer, never a crash or an
// exception; several segmenters at once on several threads; a weights-only checkpoint written by
// PyTorch opened without a config.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "core/point.hpp"
#include "core/rng.hpp"
#include "engine/cuda/install.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/run_config.hpp"
#include "engine/pipeline/segmenter.hpp"
#include "pillarseg/pillarseg.h"
#include "tests/library/fixtures.hpp"
#include "tests/support/scans.hpp"
#include "tests/support/test_support.hpp"

namespace fs = std::filesystem;

namespace pillarseg_test {

namespace {

const char* kTinyConfig =
    "grid: {x: [-6.4, 6.4], y: [-3.2, 3.2], z: [-2.5, 1.5], cell: 0.2, voxel_z: 0.5}\n"
    "model: {max_points_per_pillar: 8, pillar_channels: 4, occupancy: 2d, occupancy_channels: 2, "
    "base_width: 4, depth: 2}\n";

}  // namespace

const std::string& tiny_checkpoint() {
  static const std::string path = [] {
    const fs::path file = fs::path(PILLARSEG_BINARY_DIR) / "tests" / "library_tiny.safetensors";
    const pillarseg::RunConfig config = pillarseg::parse_run_config(kTinyConfig, "tiny");
    auto backend = pillarseg::make_cpu_backend();
    pillarseg::PillarSegNet net(config.model, *backend, /*seed=*/11);
    pillarseg::save_checkpoint(file, net, config, {}, /*with_optimizer=*/false);
    return file.string();
  }();
  return path;
}

std::vector<float> tiny_scan(int points, unsigned seed) {
  const pillarseg::RunConfig config = pillarseg::parse_run_config(kTinyConfig, "tiny");
  std::vector<float> xyzr;
  for (const pillarseg::Point& p : pillarseg::test::random_scan(points, config.model.grid, seed))
    xyzr.insert(xyzr.end(), {p.x, p.y, p.z, p.r});
  return xyzr;
}

}  // namespace pillarseg_test

using pillarseg_test::tiny_checkpoint;
using pillarseg_test::tiny_scan;

namespace {

// A segmenter with default options but `device` and `mask`; fails the test with the message.
pillarseg_segmenter* open_tiny(const char* device = "cpu", int mask = 0, const char* precision = "fp32") {
  pillarseg_options options;
  pillarseg_default_options(&options);
  options.device = device;
  options.mask_unobserved = mask;
  options.precision = precision;
  char error[512];
  pillarseg_segmenter* s = pillarseg_open(tiny_checkpoint().c_str(), nullptr, &options, error, sizeof error);
  EXPECT_NE(s, nullptr) << error;
  return s;
}

std::string open_error(const char* weights, const char* config, const pillarseg_options* options) {
  char error[512] = "untouched";
  pillarseg_segmenter* s = pillarseg_open(weights, config, options, error, sizeof error);
  EXPECT_EQ(s, nullptr);
  pillarseg_close(s);
  return error;
}

struct Output {
  std::vector<uint8_t> labels;
  std::vector<float> probabilities;
};

// Options as a program built against an older header passes them: the defaults in a struct that
// ends at `size` bytes (its struct_size), the bytes after it garbage the library must not read.
pillarseg_options older_header_options(size_t size) {
  pillarseg_options o;
  pillarseg_default_options(&o);
  std::memset(reinterpret_cast<unsigned char*>(&o) + size, 0x5a, sizeof o - size);
  o.struct_size = size;
  return o;
}

Output segment(pillarseg_segmenter* s, const std::vector<float>& xyzr) {
  int width = 0, height = 0;
  pillarseg_grid(s, &width, &height);
  const size_t cells = static_cast<size_t>(width) * static_cast<size_t>(height);
  Output out{std::vector<uint8_t>(cells), std::vector<float>(12 * cells)};
  char error[512];
  EXPECT_EQ(pillarseg_segment(s, xyzr.data(), xyzr.size() / 4, out.labels.data(), out.probabilities.data(),
                              error, sizeof error),
            0)
      << error;
  return out;
}

}  // namespace

// A program built against an older header has a shorter struct: the defaults never write past the
// size it gives (pillarseg_default_options passes its sizeof; the exported function of that name is
// what programs built against 0.3 call, with 0.3's struct).
TEST(CApi, DefaultOptionsWriteNoMoreThanTheCallersStruct) {
  constexpr unsigned char kCanary = 0xA5;
  alignas(pillarseg_options) unsigned char buffer[sizeof(pillarseg_options) + 32];
  auto* o = reinterpret_cast<pillarseg_options*>(buffer);
  const auto untouched_from = [&](std::size_t first) {
    for (std::size_t i = first; i < sizeof buffer; ++i) {
      if (buffer[i] != kCanary) return ::testing::AssertionFailure() << "byte " << i << " was written";
    }
    return ::testing::AssertionSuccess();
  };
  constexpr std::size_t kSize03 = offsetof(pillarseg_options, reflectance_none);
  std::memset(buffer, kCanary, sizeof buffer);
  (pillarseg_default_options)(o);
  EXPECT_TRUE(untouched_from(kSize03));
  EXPECT_EQ(o->struct_size, kSize03);
  EXPECT_STREQ(o->device, "cpu");
  EXPECT_STREQ(o->precision, "fp32");

  std::memset(buffer, kCanary, sizeof buffer);
  pillarseg_init_options(o, offsetof(pillarseg_options, transform));
  EXPECT_TRUE(untouched_from(offsetof(pillarseg_options, transform)));
  EXPECT_EQ(o->struct_size, offsetof(pillarseg_options, transform));
  EXPECT_EQ(o->reflectance_scale, 1.0f);
  EXPECT_EQ(o->reflectance_clip, 1);

  // A later header's longer struct: this library fills what it knows and says so in struct_size.
  std::memset(buffer, kCanary, sizeof buffer);
  pillarseg_init_options(o, sizeof buffer);
  EXPECT_TRUE(untouched_from(sizeof(pillarseg_options)));
  EXPECT_EQ(o->struct_size, sizeof(pillarseg_options));
  EXPECT_EQ(o->transform[0], 1.0);
  EXPECT_EQ(o->transform[15], 1.0);
  EXPECT_EQ(o->transform[1], 0.0);

  std::memset(buffer, kCanary, sizeof buffer);
  pillarseg_init_options(o, sizeof(std::size_t) - 1);  // cannot even hold struct_size: ignored
  EXPECT_TRUE(untouched_from(0));
}

TEST(CApi, VersionDefaultsAndClassNames) {
  EXPECT_EQ(std::string(pillarseg_version()),
            std::to_string(PILLARSEG_VERSION_MAJOR) + "." + std::to_string(PILLARSEG_VERSION_MINOR) + "." +
                std::to_string(PILLARSEG_VERSION_PATCH));
  pillarseg_options o;
  std::memset(&o, 0x5a, sizeof o);
  pillarseg_default_options(&o);
  EXPECT_EQ(o.struct_size, sizeof(pillarseg_options));
  EXPECT_STREQ(o.device, "cpu");
  EXPECT_EQ(o.threads, 0);
  EXPECT_EQ(o.cuda_device, 0);
  EXPECT_EQ(o.mask_unobserved, 0);
  EXPECT_STREQ(o.convolution, "own");
  pillarseg_init_options(nullptr, sizeof(pillarseg_options));  // ignored
  (pillarseg_default_options)(nullptr);                        // ignored
  EXPECT_STREQ(pillarseg_class_name(0), "unlabeled");
  EXPECT_STREQ(pillarseg_class_name(1), "vehicle");
  EXPECT_STREQ(pillarseg_class_name(12), "terrain");
  EXPECT_EQ(pillarseg_class_name(13), nullptr);
  EXPECT_EQ(pillarseg_class_name(-1), nullptr);
}

TEST(CApi, LabelsAndProbabilitiesAreTheEngines) {
  pillarseg::install_emulated_cuda_backend();  // this program's own engine (the library has its own)
  const std::vector<float> xyzr = tiny_scan(3000, 5);
  std::vector<pillarseg::Point> points;
  for (size_t i = 0; i + 3 < xyzr.size(); i += 4) points.push_back({xyzr[i], xyzr[i + 1], xyzr[i + 2], xyzr[i + 3]});
  for (const char* device : {"cpu", "emu"}) {
    for (const int mask : {0, 1}) {
      SCOPED_TRACE(::testing::Message() << device << (mask ? ", masked" : ""));
      pillarseg_segmenter* s = open_tiny(device, mask);
      ASSERT_NE(s, nullptr);
      int width = 0, height = 0;
      pillarseg_grid(s, &width, &height);
      EXPECT_EQ(width, 64);
      EXPECT_EQ(height, 32);
      double x_min = 0, y_min = 0, cell = 0;
      pillarseg_grid_geometry(s, &x_min, &y_min, &cell);
      EXPECT_DOUBLE_EQ(x_min, -6.4);
      EXPECT_DOUBLE_EQ(y_min, -3.2);
      EXPECT_DOUBLE_EQ(cell, 0.2);
      EXPECT_EQ(std::string(pillarseg_device_name(s)).rfind(std::string(device) == "cpu" ? "cpu" : "emu:0 (", 0),
                0u)
          << pillarseg_device_name(s);
      const Output got = segment(s, xyzr), again = segment(s, xyzr);
      EXPECT_EQ(again.labels, got.labels);
      pillarseg::SegmenterOptions options;
      options.device = device;
      options.mask_unobserved = mask != 0;
      auto engine = pillarseg::open_segmenter(tiny_checkpoint(), "", options);
      std::vector<uint8_t> labels(got.labels.size());
      std::vector<float> probabilities(got.probabilities.size());
      engine->segment(points, labels.data(), probabilities.data());
      EXPECT_EQ(got.labels, labels);
      EXPECT_EQ(got.probabilities, probabilities);
      pillarseg_close(s);
    }
  }
}

// options.precision: bf16 on the emulated CUDA backend runs the tensor-core path (the class map
// nearly the FP32 one, the probabilities close); on the CPU fp16 falls back to fp32 and says so
// through pillarseg_precision (bf16 runs there where the CPU has AVX512_BF16: test_cpu_bf16); an
// unknown precision is an error message.
TEST(CApi, PrecisionOption) {
  pillarseg::install_emulated_cuda_backend();
  const std::vector<float> xyzr = tiny_scan(3000, 5);
  pillarseg_segmenter* fp32 = open_tiny("emu", 0, "fp32");
  pillarseg_segmenter* bf16 = open_tiny("emu", 0, "bf16");
  pillarseg_segmenter* cpu = open_tiny("cpu", 0, "fp16");
  ASSERT_TRUE(fp32 && bf16 && cpu);
  EXPECT_STREQ(pillarseg_precision(fp32), "fp32");
  EXPECT_STREQ(pillarseg_precision(bf16), "bf16");
  EXPECT_STREQ(pillarseg_precision(cpu), "fp32");
  EXPECT_STREQ(pillarseg_precision(nullptr), "");
  const Output a = segment(fp32, xyzr), b = segment(bf16, xyzr);
  size_t same = 0;
  double largest = 0;
  for (size_t i = 0; i < a.labels.size(); ++i) same += a.labels[i] == b.labels[i];
  for (size_t i = 0; i < a.probabilities.size(); ++i)
    largest = std::max(largest, static_cast<double>(std::abs(a.probabilities[i] - b.probabilities[i])));
  EXPECT_GE(static_cast<double>(same), 0.99 * static_cast<double>(a.labels.size()));
  EXPECT_LT(largest, 0.05);
  EXPECT_NE(a.probabilities, b.probabilities);
  for (pillarseg_segmenter* s : {fp32, bf16, cpu}) pillarseg_close(s);
  pillarseg_options options;
  pillarseg_default_options(&options);
  options.precision = "int4";
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &options)
                .find("options->precision: expected fp32, bf16, fp16 or int8, got 'int4'"),
            std::string::npos);
  // int8 needs the scales pillarseg calibrate writes: an uncalibrated checkpoint is refused at open.
  options.precision = "int8";
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &options)
                .find("precision int8: no input scale for the convolutions (the weights are not calibrated"),
            std::string::npos);
}

TEST(CApi, BadFilesAndOptionsAreMessages) {
  const std::string missing = (pillarseg::test::temp_dir() / "nope.safetensors").string();
  EXPECT_NE(open_error(missing.c_str(), nullptr, nullptr).find("nope.safetensors: no such file"), std::string::npos);
  EXPECT_NE(open_error(nullptr, nullptr, nullptr).find("weights_path is NULL"), std::string::npos);
  // A truncated checkpoint names the file.
  const fs::path truncated = pillarseg::test::temp_dir() / "truncated.safetensors";
  {
    std::ifstream in(tiny_checkpoint(), std::ios::binary);
    std::vector<char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    std::ofstream(truncated, std::ios::binary).write(bytes.data(), static_cast<std::streamsize>(bytes.size() / 2));
  }
  EXPECT_NE(open_error(truncated.string().c_str(), nullptr, nullptr).find("truncated.safetensors"), std::string::npos);
  // A config that names a missing file, a device that does not exist, fields out of range.
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), "/no/such/config.yaml", nullptr).find("config.yaml"),
            std::string::npos);
  pillarseg_options o;
  pillarseg_default_options(&o);
  o.device = "tpu";
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &o).find("\"cpu\", \"cuda\" or \"emu\", got \"tpu\""),
            std::string::npos);
  pillarseg_default_options(&o);
  o.threads = -2;
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &o).find("threads must be >= 0"), std::string::npos);
  pillarseg_default_options(&o);
  o.struct_size = 0;
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &o).find("struct_size"), std::string::npos);
  pillarseg_default_options(&o);
  o.device = "cpu";
  o.convolution = "cudnn";
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &o).find("--conv cudnn needs --device cuda"),
            std::string::npos);
  // The error buffer: truncated and terminated, or absent.
  char small[8];
  std::memset(small, 'x', sizeof small);
  EXPECT_EQ(pillarseg_open(missing.c_str(), nullptr, nullptr, small, sizeof small), nullptr);
  EXPECT_EQ(std::strlen(small), 7u);
  EXPECT_EQ(pillarseg_open(missing.c_str(), nullptr, nullptr, nullptr, 0), nullptr);
  EXPECT_EQ(pillarseg_open(missing.c_str(), nullptr, nullptr, small, 0), nullptr);
}

TEST(CApi, BadSegmentArgumentsAreMessages) {
  pillarseg_segmenter* s = open_tiny();
  ASSERT_NE(s, nullptr);
  std::vector<uint8_t> labels(64 * 32);
  const std::vector<float> xyzr = tiny_scan(10, 6);
  char error[512];
  EXPECT_NE(pillarseg_segment(nullptr, xyzr.data(), 10, labels.data(), nullptr, error, sizeof error), 0);
  EXPECT_NE(std::string(error).find("the segmenter is NULL"), std::string::npos) << error;
  EXPECT_NE(pillarseg_segment(s, xyzr.data(), 10, nullptr, nullptr, error, sizeof error), 0);
  EXPECT_NE(std::string(error).find("labels is NULL: it must hold width x height = 2048 bytes"), std::string::npos)
      << error;
  EXPECT_NE(pillarseg_segment(s, nullptr, 10, labels.data(), nullptr, error, sizeof error), 0);
  EXPECT_NE(std::string(error).find("points_xyzr is NULL for 10 points"), std::string::npos) << error;
  EXPECT_NE(pillarseg_segment(s, xyzr.data(), size_t{1} << 40, labels.data(), nullptr, error, sizeof error), 0);
  EXPECT_NE(std::string(error).find("at most 2147483646 a scan"), std::string::npos) << error;
  // An empty scan, and points that are all non-finite, are valid scans.
  EXPECT_EQ(pillarseg_segment(s, nullptr, 0, labels.data(), nullptr, error, sizeof error), 0) << error;
  EXPECT_STREQ(error, "");
  const std::vector<float> nan(40, std::numeric_limits<float>::quiet_NaN());
  EXPECT_EQ(pillarseg_segment(s, nan.data(), 10, labels.data(), nullptr, error, sizeof error), 0) << error;
  pillarseg_close(s);
  pillarseg_close(nullptr);
  // Queries on a NULL segmenter answer zeros.
  int width = 7, height = 7;
  pillarseg_grid(nullptr, &width, &height);
  EXPECT_EQ(width, 0);
  EXPECT_EQ(height, 0);
  EXPECT_STREQ(pillarseg_device_name(nullptr), "");
}

// Point counts too large for the 32-bit point indices or for the memory are refused before a point
// is read (the buffers here hold 10): an error message, then the segmenter works as before.
TEST(CApi, PointCountsBeyondTheIndicesOrTheMemoryAreMessages) {
  pillarseg_segmenter* s = open_tiny();
  ASSERT_NE(s, nullptr);
  std::vector<uint8_t> labels(64 * 32);
  const std::vector<float> xyzr = tiny_scan(10, 7);
  char error[512];
  EXPECT_NE(pillarseg_segment(s, xyzr.data(), SIZE_MAX / 8, labels.data(), nullptr, error, sizeof error), 0);
  EXPECT_NE(std::string(error).find("pillarseg_segment: 2305843009213693951 points overflow the 32-bit point "
                                    "indices (at most 2147483646 a scan)"),
            std::string::npos)
      << error;
  setenv("PILLARSEG_MEMORY_LIMIT", "256M", 1);
  EXPECT_NE(pillarseg_segment(s, xyzr.data(), size_t{1} << 30, labels.data(), nullptr, error, sizeof error), 0);
  unsetenv("PILLARSEG_MEMORY_LIMIT");
  EXPECT_NE(std::string(error).find("pillarseg_segment: a scan of 1073741824 points (buffers for 1342177280 "
                                    "points, "),
            std::string::npos)
      << error;
  EXPECT_NE(std::string(error).find("would need "), std::string::npos) << error;
  EXPECT_NE(std::string(error).find("more than the 256.0 MiB of memory available (PILLARSEG_MEMORY_LIMIT=256M)"),
            std::string::npos)
      << error;
  EXPECT_EQ(pillarseg_segment(s, xyzr.data(), 10, labels.data(), nullptr, error, sizeof error), 0) << error;
  pillarseg_close(s);
}

TEST(CApi, SegmentersOnSeveralThreadsGiveTheirSingleThreadResults) {
  struct Job {
    const char* device;
    int threads;
    std::vector<float> scan;
    Output expected, got;
    pillarseg_segmenter* segmenter = nullptr;
  };
  std::vector<Job> jobs = {{"cpu", 1, tiny_scan(2500, 7), {}, {}}, {"cpu", 2, tiny_scan(1800, 8), {}, {}},
                           {"emu", 1, tiny_scan(900, 9), {}, {}}};
  for (Job& job : jobs) {
    pillarseg_options o;
    pillarseg_default_options(&o);
    o.device = job.device;
    o.threads = job.threads;
    char error[512];
    job.segmenter = pillarseg_open(tiny_checkpoint().c_str(), nullptr, &o, error, sizeof error);
    ASSERT_NE(job.segmenter, nullptr) << error;
    job.expected = segment(job.segmenter, job.scan);
  }
  std::vector<std::thread> threads;
  for (Job& job : jobs) {
    threads.emplace_back([&job] {
      for (int round = 0; round < 3; ++round) job.got = segment(job.segmenter, job.scan);
    });
  }
  for (std::thread& t : threads) t.join();
  for (Job& job : jobs) {
    EXPECT_EQ(job.got.labels, job.expected.labels) << job.device;
    EXPECT_EQ(job.got.probabilities, job.expected.probabilities) << job.device;
    pillarseg_close(job.segmenter);
  }
}

TEST(CApi, WeightsOnlyPyTorchCheckpointOpensWithoutAConfig) {
  const fs::path file = fs::path(PILLARSEG_SOURCE_DIR) / "tests/golden/weights_only_pillars_occ2d_bilinear_bce.safetensors";
  char error[512];
  pillarseg_segmenter* s = pillarseg_open(file.string().c_str(), nullptr, nullptr, error, sizeof error);
  ASSERT_NE(s, nullptr) << error;
  int width = 0, height = 0;
  pillarseg_grid(s, &width, &height);
  EXPECT_EQ(width, 1000);  // the paper's grid
  EXPECT_EQ(height, 500);
  const Output out = segment(s, tiny_scan(4000, 10));
  for (uint8_t k : out.labels) ASSERT_TRUE(k >= 1 && k <= 12);
  pillarseg_close(s);
  // The 3D-occupancy file's stream reads 4 layers, which the paper's grid (20) does not have.
  const fs::path occupancy_3d = fs::path(PILLARSEG_SOURCE_DIR) / "tests/golden/weights_only_pillars_occ3d_transposed_ce.safetensors";
  EXPECT_NE(open_error(occupancy_3d.string().c_str(), nullptr, nullptr).find("occupancy.conv.weight has 4 input channels"),
            std::string::npos);
}

// pillarseg_read_points: a point file's records as stored (here a KITTI .bin and the same points
// as a .npy), freed with pillarseg_free; every failure a message with *points_xyzr NULL.
TEST(CApi, ReadPointsAndFree) {
  const fs::path dir = pillarseg::test::temp_dir();
  const std::vector<float> xyzr = {1.5f, -2.0f, 0.25f, 0.5f, -30.0f, 12.5f, -1.75f, 200.0f};
  { std::ofstream(dir / "two.bin", std::ios::binary).write(reinterpret_cast<const char*>(xyzr.data()), 32); }
  std::string dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 4), }";
  dict.resize(128 - 10 - 1, ' ');
  dict += '\n';
  std::string npy = std::string("\x93NUMPY\x01\x00", 8) + static_cast<char>(dict.size()) + '\0' + dict;
  npy.append(reinterpret_cast<const char*>(xyzr.data()), 32);
  { std::ofstream(dir / "two.npy", std::ios::binary) << npy; }
  const std::vector<std::pair<const char*, const char*>> reads = {
      {"two.bin", nullptr}, {"two.npy", nullptr}, {"two.bin", "kitti"}};
  for (const auto& [file, format] : reads) {
    SCOPED_TRACE(file);
    float* points = nullptr;
    size_t n = 0;
    char error[256] = "untouched";
    ASSERT_EQ(pillarseg_read_points((dir / file).c_str(), format, &points, &n, error, sizeof error), 0) << error;
    EXPECT_STREQ(error, "");
    ASSERT_EQ(n, 2u);
    EXPECT_EQ(std::vector<float>(points, points + 8), xyzr);
    pillarseg_free(points);
  }
  pillarseg_free(nullptr);
  const auto read_error = [&](const char* path, const char* format) {
    float sentinel = 0;
    float* points = &sentinel;  // must come back NULL
    size_t n = 7;
    char error[512] = "";
    EXPECT_NE(pillarseg_read_points(path, format, &points, &n, error, sizeof error), 0);
    EXPECT_EQ(points, nullptr);
    EXPECT_EQ(n, 0u);
    return std::string(error);
  };
  EXPECT_NE(read_error((dir / "two.bin").c_str(), "npy").find("pillarseg_read_points: " + (dir / "two.bin").string() +
                                                               ": not a NumPy .npy file"),
            std::string::npos);
  EXPECT_NE(read_error((dir / "two.bin").c_str(), "las").find("format 'las': unknown point format"), std::string::npos);
  EXPECT_NE(read_error((dir / "none.pcd").c_str(), nullptr).find("none.pcd: cannot open"), std::string::npos);
  EXPECT_NE(read_error(nullptr, nullptr).find("path is NULL"), std::string::npos);
  char error[256];
  EXPECT_NE(pillarseg_read_points((dir / "two.bin").c_str(), nullptr, nullptr, nullptr, error, sizeof error), 0);
  EXPECT_NE(std::string(error).find("must not be NULL"), std::string::npos) << error;
}

// The options' input mapping: a segmenter opened with a transform and a reflectance scale gives
// what the default one gives on the points mapped by hand; an options struct of the previous
// version's size (without these fields) opens and segments as before, whatever follows it.
TEST(CApi, InputMappingOptions) {
  std::vector<float> xyzr = tiny_scan(3000, 8);
  for (size_t i = 3; i < xyzr.size(); i += 4) xyzr[i] *= 255;  // an 8-bit sensor
  std::vector<float> mapped = xyzr;
  for (size_t i = 0; i < mapped.size(); i += 4) {
    const float x = mapped[i], y = mapped[i + 1];
    // Yaw 90 degrees, 0.5 m up (in double, as the library maps), reflectance / 255 (in float).
    mapped[i] = -y, mapped[i + 1] = x, mapped[i + 2] = static_cast<float>(static_cast<double>(mapped[i + 2]) + 0.5);
    mapped[i + 3] = std::min(1.0f, std::max(0.0f, (1.0f / 255.0f) * mapped[i + 3]));
  }
  pillarseg_options options;
  pillarseg_default_options(&options);
  EXPECT_EQ(options.reflectance_none, 0);
  EXPECT_EQ(options.reflectance_scale, 1.0f);
  EXPECT_EQ(options.reflectance_offset, 0.0f);
  EXPECT_EQ(options.reflectance_clip, 1);
  for (int k = 0; k < 16; ++k) EXPECT_EQ(options.transform[k], k % 5 == 0 ? 1.0 : 0.0);
  const double yaw_up[16] = {0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 0.5, 0, 0, 0, 1};
  std::copy(yaw_up, yaw_up + 16, options.transform);
  options.reflectance_scale = 1.0f / 255.0f;
  char error[512];
  pillarseg_segmenter* with = pillarseg_open(tiny_checkpoint().c_str(), nullptr, &options, error, sizeof error);
  ASSERT_NE(with, nullptr) << error;
  pillarseg_segmenter* plain = open_tiny();
  ASSERT_NE(plain, nullptr);
  const Output by_options = segment(with, xyzr), by_hand = segment(plain, mapped), unmapped = segment(plain, xyzr);
  EXPECT_EQ(by_options.labels, by_hand.labels);
  EXPECT_EQ(by_options.probabilities, by_hand.probabilities);
  EXPECT_NE(by_options.probabilities, unmapped.probabilities);
  pillarseg_close(with);

  // The previous version's struct: its size ends before reflectance_none; the bytes after it are
  // not read.
  const pillarseg_options old = older_header_options(offsetof(pillarseg_options, reflectance_none));
  pillarseg_segmenter* previous = pillarseg_open(tiny_checkpoint().c_str(), nullptr, &old, error, sizeof error);
  ASSERT_NE(previous, nullptr) << error;
  EXPECT_EQ(segment(previous, xyzr).probabilities, unmapped.probabilities);
  pillarseg_close(previous);
  pillarseg_close(plain);

  pillarseg_default_options(&options);
  options.transform[15] = 2;
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &options)
                .find("options->transform: the transform's bottom row is [0 0 0 2], expected [0 0 0 1]"),
            std::string::npos);
  pillarseg_default_options(&options);
  options.reflectance_scale = std::numeric_limits<float>::infinity();
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &options).find("reflectance_offset must be finite"),
            std::string::npos);
}

// options.flips: the engine's mirrored copies (the same bits as a ScanSegmenter with flips), a
// 0.4 struct (which ends before flips) runs one pass, and a value or grid the mirrors do not fit
// is an error message.
TEST(CApi, FlipsOption) {
  const std::vector<float> xyzr = tiny_scan(3000, 9);
  std::vector<pillarseg::Point> points;
  for (size_t i = 0; i + 3 < xyzr.size(); i += 4) points.push_back({xyzr[i], xyzr[i + 1], xyzr[i + 2], xyzr[i + 3]});
  pillarseg_options options;
  pillarseg_default_options(&options);
  EXPECT_EQ(options.flips, 1);
  options.flips = 4;
  char error[512];
  pillarseg_segmenter* flipping = pillarseg_open(tiny_checkpoint().c_str(), nullptr, &options, error, sizeof error);
  ASSERT_NE(flipping, nullptr) << error;
  pillarseg_segmenter* plain = open_tiny();
  ASSERT_NE(plain, nullptr);
  const Output four = segment(flipping, xyzr), one = segment(plain, xyzr);
  pillarseg::SegmenterOptions engine_options;
  engine_options.flips = 4;
  auto engine = pillarseg::open_segmenter(tiny_checkpoint(), "", engine_options);
  std::vector<uint8_t> labels(four.labels.size());
  std::vector<float> probabilities(four.probabilities.size());
  engine->segment(points, labels.data(), probabilities.data());
  EXPECT_EQ(four.labels, labels);
  EXPECT_EQ(four.probabilities, probabilities);
  EXPECT_NE(four.probabilities, one.probabilities);
  pillarseg_close(flipping);

  const pillarseg_options old = older_header_options(offsetof(pillarseg_options, flips));
  pillarseg_segmenter* previous = pillarseg_open(tiny_checkpoint().c_str(), nullptr, &old, error, sizeof error);
  ASSERT_NE(previous, nullptr) << error;
  EXPECT_EQ(segment(previous, xyzr).probabilities, one.probabilities);
  pillarseg_close(previous);
  pillarseg_close(plain);

  options.flips = 3;
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), nullptr, &options)
                .find("options->flips must be 1 (the scan alone), 2 (and y -> -y) or 4 (and x -> -x, and both), got 3"),
            std::string::npos);
  // A grid reaching further to the left than to the right: no mirror y -> -y maps it onto itself.
  const fs::path config = fs::path(PILLARSEG_BINARY_DIR) / "tests" / "library_flips_grid.yaml";
  {
    std::ofstream out(config);
    out << "grid: {x: [-6.4, 6.4], y: [-3.2, 4.8], z: [-2.5, 1.5], cell: 0.2, voxel_z: 0.5}\n"
           "model: {max_points_per_pillar: 8, pillar_channels: 4, occupancy: 2d, occupancy_channels: 2, "
           "base_width: 4, depth: 2}\n";
  }
  options.flips = 2;
  EXPECT_NE(open_error(tiny_checkpoint().c_str(), config.c_str(), &options).find("grid.y is [-3.2, 4.8]"),
            std::string::npos);
  options.flips = 1;
  pillarseg_segmenter* wide = pillarseg_open(tiny_checkpoint().c_str(), config.c_str(), &options, error, sizeof error);
  EXPECT_NE(wide, nullptr) << error;
  pillarseg_close(wide);
}

