#include "engine/model/architecture.hpp"

#include <fmt/format.h>

#include <string>

#include "core/error.hpp"

namespace pillarseg {

namespace {

constexpr const char* kPfn = "vfe.pfn_layers.0.linear.weight";
constexpr const char* kOccupancy = "occupancy.conv.weight";
constexpr const char* kHead = "segmentation_head.outc.conv.weight";

std::string down_conv(int level) {
  return fmt::format("segmentation_head.down{}.maxpool_conv.1.double_conv.0.weight", level);
}

// The shape of `name`, which must have `rank` dimensions.
const Shape& shape_of(const weights::SafeTensors& file, const std::string& name, size_t rank,
                      const char* expected) {
  const Shape& shape = file.at(name).shape;
  PS_CHECK(shape.size() == rank, "{}: {} has shape {}, expected {}; the file fits no PillarSegNet",
           file.source(), name, shape_str(shape), expected);
  return shape;
}

}  // namespace

ModelConfig model_config_from_tensors(const weights::SafeTensors& file, const GridSpec& grid) {
  ModelConfig c;
  c.grid = grid;
  PS_CHECK(file.contains(kHead),
           "{}: no tensor {} (the 1x1 head): not a PillarSegNet checkpoint with the authors' module "
           "names",
           file.source(), kHead);
  const Shape& head = shape_of(file, kHead, 4, "(12, b, 1, 1)");
  PS_CHECK(head[0] == 12 && head[2] == 1 && head[3] == 1,
           "{}: {} has shape {}, expected (12, b, 1, 1) (12 classes, a 1x1 kernel)", file.source(),
           kHead, shape_str(head));
  c.base_width = static_cast<int>(head[1]);

  c.pillar_input = file.contains(kPfn);
  if (c.pillar_input) {
    const Shape& pfn = shape_of(file, kPfn, 2, "(C, 10)");
    PS_CHECK(pfn[1] == 10, "{}: {} has shape {}, expected (C, 10): 10 features per decorated point",
             file.source(), kPfn, shape_str(pfn));
    c.pillar_channels = static_cast<int>(pfn[0]);
  }
  if (file.contains(kOccupancy)) {
    const Shape& occupancy = shape_of(file, kOccupancy, 4, "(Q, I, 3, 3)");
    PS_CHECK(occupancy[2] == 3 && occupancy[3] == 3, "{}: {} has shape {}, expected a 3x3 kernel",
             file.source(), kOccupancy, shape_str(occupancy));
    c.occupancy_channels = static_cast<int>(occupancy[0]);
    if (occupancy[1] == 1) {
      c.occupancy = OccupancyInput::Observability2D;
    } else if (occupancy[1] == grid.layers()) {
      c.occupancy = OccupancyInput::Occupancy3D;
    } else {
      PS_FAIL("{}: {} has {} input channels: 1 (2D observability) or {} (3D occupancy, the z range "
              "[{}, {}) m in {} m voxels) expected; pass --config with the grid it was trained on",
              file.source(), kOccupancy, occupancy[1], grid.layers(), grid.z_min, grid.z_max,
              grid.voxel_z);
    }
  }

  PS_CHECK(file.contains(down_conv(1)), "{}: no tensor {}: the U-Net has no first Down block",
           file.source(), down_conv(1));
  const Shape& first = shape_of(file, down_conv(1), 4, "(2b, I, 3, 3)");
  const int64_t streams = (c.pillar_input ? c.pillar_channels : 0) +
                          (c.occupancy != OccupancyInput::None ? c.occupancy_channels : 0);
  c.grid_map_input = first[1] == streams + 6;
  PS_CHECK(first[1] == streams || c.grid_map_input,
           "{}: {} reads {} input channels, but the streams give {} ({}{}), or {} with the grid-map "
           "layers",
           file.source(), down_conv(1), first[1], streams,
           c.pillar_input ? fmt::format("{} pillar", c.pillar_channels) : "no pillar",
           c.occupancy != OccupancyInput::None ? fmt::format(" + {} occupancy", c.occupancy_channels)
                                               : "",
           streams + 6);
  c.depth = 0;
  while (file.contains(down_conv(c.depth + 1))) ++c.depth;
  c.transposed = file.contains("segmentation_head.up1.up.weight");
  PS_CHECK(c.depth >= 1 && c.depth <= 6, "{}: {} Down blocks; a PillarSegNet has 1 to 6",
           file.source(), c.depth);
  c.validate();
  return c;
}

}  // namespace pillarseg
