// Every shipped config parses, validates and says what its comment says; bad configs give
// errors that name the file and the key.
#include <gtest/gtest.h>

#include <filesystem>

#include "core/error.hpp"
#include "engine/model/run_config.hpp"

using namespace pillarseg;
namespace fs = std::filesystem;

TEST(Configs, EveryShippedConfigLoads) {
  int n = 0;
  for (const auto& entry : fs::directory_iterator(fs::path(PILLARSEG_SOURCE_DIR) / "configs")) {
    if (entry.path().extension() != ".yaml") continue;
    const RunConfig c = load_run_config(entry.path());
    EXPECT_NO_THROW(c.model.validate()) << entry.path();
    ++n;
  }
  EXPECT_GE(n, 9);
}

TEST(Configs, PaperSettings) {
  const fs::path dir = fs::path(PILLARSEG_SOURCE_DIR) / "configs";
  const RunConfig p = load_run_config(dir / "pillar_3d_dense.yaml");
  EXPECT_EQ(p.model.grid.width(), 1000);
  EXPECT_EQ(p.model.grid.height(), 500);
  EXPECT_EQ(p.model.occupancy, OccupancyInput::Occupancy3D);
  EXPECT_EQ(p.model.input_channels(), 64 + 16);
  EXPECT_EQ(p.train.ground_truth, GroundTruthKind::dense);
  EXPECT_EQ(p.train.coefficients[1], 5.0f);  // vehicle, dense
  EXPECT_EQ(p.train.coefficients[2], 8.0f);
  EXPECT_EQ(p.train.epochs, 30);
  EXPECT_EQ(p.train.batch_size, 2);
  EXPECT_EQ(p.eval.sequences, std::vector<int>{8});
  const RunConfig g = load_run_config(dir / "gridmap_sparse.yaml");
  EXPECT_FALSE(g.model.pillar_input);
  EXPECT_EQ(g.model.input_channels(), 6);
  EXPECT_EQ(g.train.coefficients[1], 2.0f);  // vehicle, sparse
}

TEST(Configs, ErrorsNameTheKey) {
  const auto message = [](const std::string& text) {
    try {
      parse_run_config(text, "my.yaml");
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  EXPECT_NE(message("model: {base_widht: 8}").find("model.base_widht"), std::string::npos);
  EXPECT_NE(message("train: {loss: hinge}").find("train.loss: expected ce, bce or ce+lovasz, got 'hinge'"),
            std::string::npos);
  EXPECT_EQ(parse_run_config("train: {loss: ce+lovasz}", "my.yaml").train.loss, LossKind::CrossEntropyLovasz);
  EXPECT_EQ(parse_run_config("train: {loss: bce}", "my.yaml").train.loss, LossKind::Bce);
  EXPECT_NE(message("modle: {}").find("modle"), std::string::npos);
  EXPECT_NE(message("model: {occupancy: 4d}").find("my.yaml"), std::string::npos);
  EXPECT_NE(message("train: {coefficients: {car: 3}}").find("car"), std::string::npos);
  EXPECT_NE(message("grid: {x: [0, 1.6], y: [0, 0.8], cell: 0.1}\nmodel: {depth: 4}").find("too small"),
            std::string::npos);
  EXPECT_NE(message("train: {epochs: 0}").find("train.epochs"), std::string::npos);
  EXPECT_NE(message("train: {precise_bn_batches: -1}").find("train.precise_bn_batches"), std::string::npos);
  EXPECT_NE(message("train: {epochs: 4, average_epochs: 5, precise_bn_batches: 2}").find("train.average_epochs"),
            std::string::npos);
  EXPECT_NE(message("train: {average_epochs: -1}").find("train.average_epochs"), std::string::npos);
  EXPECT_NE(message("train: {epochs: 4, average_epochs: 2}").find("precise_bn_batches"), std::string::npos);
  EXPECT_EQ(parse_run_config("train: {epochs: 4, average_epochs: 4, precise_bn_batches: 2}", "my.yaml")
                .train.average_epochs,
            4);
  EXPECT_EQ(parse_run_config("train: {}", "my.yaml").train.average_epochs, 0);
  EXPECT_NE(message("train: {gradient_bucket_mb: -0.5}").find("train.gradient_bucket_mb"), std::string::npos);
  EXPECT_EQ(parse_run_config("train: {gradient_bucket_mb: 0.25}", "my.yaml").train.gradient_bucket_mb, 0.25);
  EXPECT_EQ(parse_run_config("train: {}", "my.yaml").train.gradient_bucket_mb, 4.0);
  EXPECT_NE(message("eval: {flips: 3}").find("eval.flips: 3 mirrored copies"), std::string::npos);
  EXPECT_NE(message("grid: {y: [-20, 25]}\neval: {flips: 2}").find("grid.y is [-20, 25]"), std::string::npos);
  EXPECT_NE(message("grid: {x: [0, 100]}\neval: {flips: 4}").find("grid.x is [0, 100]"), std::string::npos);
  EXPECT_EQ(parse_run_config("grid: {x: [0, 100]}\neval: {flips: 2}", "my.yaml").eval.flips, 2);
  EXPECT_EQ(parse_run_config("eval: {flips: 4}", "my.yaml").eval.flips, 4);
  EXPECT_EQ(parse_run_config("eval: {}", "my.yaml").eval.flips, 1);
}
