#include "engine/model/config.hpp"

#include <yaml-cpp/yaml.h>

#include <cmath>

#include "core/error.hpp"
#include "core/memory_budget.hpp"
#include "engine/model/memory_estimate.hpp"

namespace pillarseg {

int ModelConfig::input_channels() const {
  return (pillar_input ? pillar_channels : 0) + (occupancy != OccupancyInput::None ? occupancy_channels : 0) +
         (grid_map_input ? 6 : 0);
}

int ModelConfig::occupancy_input_channels() const {
  switch (occupancy) {
    case OccupancyInput::Observability2D: return 1;
    case OccupancyInput::Occupancy3D: return grid.layers();
    case OccupancyInput::None: return 0;
  }
  return 0;
}

std::string occupancy_name(OccupancyInput o) {
  switch (o) {
    case OccupancyInput::Observability2D: return "2d";
    case OccupancyInput::Occupancy3D: return "3d";
    case OccupancyInput::None: return "none";
  }
  return "none";
}

void ModelConfig::validate() const {
  const auto multiple = [](double span, double step) {
    const double n = span / step;
    return std::abs(n - std::round(n)) < 1e-6 && n >= 1;
  };
  PS_CHECK(grid.cell > 0, "grid.cell must be > 0, got {}", grid.cell);
  // Cells and layers along each axis are ints (GridSpec::width() etc.): checked before they are
  // rounded (a span that is not a number fails the whole-multiple checks below).
  const auto axis = [](double span, double step, const char* name, const char* range) {
    const double n = span / step;
    PS_CHECK(!(step > 0 && n > static_cast<double>(kMaxInt32Index)),
             "grid: {} / {} m = {:.4g} {} overflows the 32-bit cell indices (at most {})", range, step, n, name,
             kMaxInt32Index);
  };
  axis(grid.x_max - grid.x_min, grid.cell, "cells along x", "the x range");
  axis(grid.y_max - grid.y_min, grid.cell, "cells along y", "the y range");
  axis(grid.z_max - grid.z_min, grid.voxel_z, "layers", "the z range");
  PS_CHECK(multiple(grid.x_max - grid.x_min, grid.cell) && multiple(grid.y_max - grid.y_min, grid.cell),
           "grid: x and y ranges must be positive whole multiples of the cell size {}", grid.cell);
  PS_CHECK(multiple(grid.z_max - grid.z_min, grid.voxel_z), "grid: the z range must be a whole multiple of voxel_z {}",
           grid.voxel_z);
  PS_CHECK(max_points_per_pillar >= 1, "model.max_points_per_pillar must be >= 1, got {}", max_points_per_pillar);
  PS_CHECK(max_pillars >= 0, "model.max_pillars must be >= 0 (0 keeps all), got {}", max_pillars);
  PS_CHECK(pillar_channels >= 1 && occupancy_channels >= 1, "model: channel counts must be >= 1");
  require_int32_count({int64_t{pillar_channels} + occupancy_channels + 6},
                      fmt::format("model.pillar_channels {} + occupancy_channels {} + 6", pillar_channels,
                                  occupancy_channels),
                      "channel counts");
  PS_CHECK(input_channels() > 0, "model: no input stream enabled (pillars, occupancy or grid_map)");
  PS_CHECK(base_width >= 2 && base_width % 2 == 0, "model.base_width must be even and >= 2, got {}", base_width);
  PS_CHECK(depth >= 1 && depth <= 6, "model.depth must be in 1..6, got {}", depth);
  require_int32_count({base_width, int64_t{1} << depth},
                      fmt::format("model.base_width {} x 2^depth {}", base_width, depth), "channel counts");
  PS_CHECK(num_classes == 12, "model.num_classes must be 12 (the class table), got {}", num_classes);
  const int min_side = 1 << depth;
  PS_CHECK(grid.width() >= min_side && grid.height() >= min_side,
           "grid {}x{} is too small for a U-Net of depth {} (needs at least {} cells a side)", grid.width(),
           grid.height(), depth, min_side);
  check_index_limits(*this, 1);
}

GridSpec grid_from_yaml(const YAML::Node& node, const std::string& source) {
  GridSpec g;
  if (!node) return g;
  try {
    if (node["x"]) {
      auto v = node["x"].as<std::vector<double>>();
      PS_CHECK(v.size() == 2, "{}: grid.x needs [min, max]", source);
      g.x_min = v[0], g.x_max = v[1];
    }
    if (node["y"]) {
      auto v = node["y"].as<std::vector<double>>();
      PS_CHECK(v.size() == 2, "{}: grid.y needs [min, max]", source);
      g.y_min = v[0], g.y_max = v[1];
    }
    if (node["z"]) {
      auto v = node["z"].as<std::vector<double>>();
      PS_CHECK(v.size() == 2, "{}: grid.z needs [min, max]", source);
      g.z_min = v[0], g.z_max = v[1];
    }
    if (node["cell"]) g.cell = node["cell"].as<double>();
    if (node["voxel_z"]) g.voxel_z = node["voxel_z"].as<double>();
  } catch (const YAML::Exception& e) {
    PS_FAIL("{}: grid: {}", source, e.what());
  }
  return g;
}

ModelConfig model_config_from_yaml(const YAML::Node& root, const std::string& source) {
  ModelConfig c;
  c.grid = grid_from_yaml(root["grid"], source);
  const YAML::Node m = root["model"];
  if (m) {
    try {
      for (const auto& kv : m) {
        const std::string key = kv.first.as<std::string>();
        const YAML::Node& v = kv.second;
        if (key == "max_points_per_pillar") c.max_points_per_pillar = v.as<int>();
        else if (key == "max_pillars") c.max_pillars = v.as<int>();
        else if (key == "pillars") c.pillar_input = v.as<bool>();
        else if (key == "reflectance") c.reflectance = v.as<bool>();
        else if (key == "pillar_channels") c.pillar_channels = v.as<int>();
        else if (key == "occupancy") {
          const std::string o = v.as<std::string>();
          if (o == "none") c.occupancy = OccupancyInput::None;
          else if (o == "2d") c.occupancy = OccupancyInput::Observability2D;
          else if (o == "3d") c.occupancy = OccupancyInput::Occupancy3D;
          else PS_FAIL("{}: model.occupancy must be none, 2d or 3d, got '{}'", source, o);
        } else if (key == "occupancy_channels") c.occupancy_channels = v.as<int>();
        else if (key == "grid_map") c.grid_map_input = v.as<bool>();
        else if (key == "base_width") c.base_width = v.as<int>();
        else if (key == "depth") c.depth = v.as<int>();
        else if (key == "upsampling") {
          const std::string u = v.as<std::string>();
          PS_CHECK(u == "bilinear" || u == "transposed", "{}: model.upsampling must be bilinear or transposed, got '{}'",
                   source, u);
          c.transposed = u == "transposed";
        } else if (key == "num_classes") c.num_classes = v.as<int>();
        else PS_FAIL("{}: unknown key model.{}", source, key);
      }
    } catch (const YAML::Exception& e) {
      PS_FAIL("{}: model: {}", source, e.what());
    }
  }
  try {
    c.validate();
  } catch (const Error& e) {
    PS_FAIL("{}: {}", source, e.what());
  }
  return c;
}

void check_flips(int flips, const GridSpec& grid, const std::string& what) {
  PS_CHECK(flips == 1 || flips == 2 || flips == 4,
           "{}: {} mirrored copies of the scan: expected 1 (none), 2 (and y -> -y) or 4 (and x -> -x, and both)",
           what, flips);
  PS_CHECK(flips == 1 || grid.y_min == -grid.y_max,
           "{} {}: the mirror y -> -y maps the grid onto itself only when it is symmetric about the sensor; "
           "grid.y is [{}, {}]",
           what, flips, grid.y_min, grid.y_max);
  PS_CHECK(flips < 4 || grid.x_min == -grid.x_max,
           "{} {}: the mirror x -> -x maps the grid onto itself only when it is symmetric about the sensor; "
           "grid.x is [{}, {}] (2 mirrors y alone)",
           what, flips, grid.x_min, grid.x_max);
}

}  // namespace pillarseg
