// ModelConfig: the PillarSegNet variant (DESIGN.md section 2): grid, pillar settings, the
// input streams (pillars, 2D observability or 3D occupancy, the grid-map baseline), and the
// U-Net (base width b, depth, bilinear or transposed-convolution upsampling). Read from the
// `model:` and `grid:` sections of a YAML config.
#pragma once

#include <string>

#include "core/grid.hpp"

namespace YAML {
class Node;
}

namespace pillarseg {

enum class OccupancyInput { None, Observability2D, Occupancy3D };

struct ModelConfig {
  GridSpec grid;
  int max_points_per_pillar = 20;  // N
  int max_pillars = 0;             // P; 0 keeps every non-empty pillar
  bool pillar_input = true;        // the PointNet pillar stream (C channels)
  // false: the network never sees reflectance (every point's r is taken as 0 in training and
  // inference), for sensors that give none.
  bool reflectance = true;
  int pillar_channels = 64;        // C
  OccupancyInput occupancy = OccupancyInput::None;
  int occupancy_channels = 16;  // Q
  bool grid_map_input = false;  // Bieder et al.'s six hand-crafted layers
  int base_width = 64;          // b
  int depth = 4;                // number of Down (and Up) blocks
  bool transposed = false;      // ConvTranspose upsampling instead of bilinear
  int num_classes = 12;

  // Channels entering the U-Net: C (if pillars) + Q (if occupancy) + 6 (if grid map).
  int input_channels() const;
  // Channels of the raw occupancy input: 1 (2D observability) or grid.layers() (3D).
  int occupancy_input_channels() const;
  void validate() const;  // throws pillarseg::Error naming the bad field
};

ModelConfig model_config_from_yaml(const YAML::Node& root, const std::string& source);
GridSpec grid_from_yaml(const YAML::Node& node, const std::string& source);
std::string occupancy_name(OccupancyInput o);

// Test-time flips (SegmenterOptions::flips, eval.flips): 1, 2 (and the mirror y -> -y) or 4 (and
// x -> -x, and both); a mirror maps the grid onto itself only where the grid is symmetric about
// the sensor on that axis. Errors name `what` (the option or key), the value and the grid.
void check_flips(int flips, const GridSpec& grid, const std::string& what);

}  // namespace pillarseg
