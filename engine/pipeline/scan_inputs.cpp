#include "engine/pipeline/scan_inputs.hpp"

#include <cmath>
#include <cstring>

#include "core/error.hpp"
#include "host/grid_map_features.hpp"
#include "host/point_decoration.hpp"
#include "host/raywalk.hpp"

namespace pillarseg {

ScanInputs compute_scan_inputs(const std::vector<Point>& scan_points, const Eigen::Vector3d& origin,
                               const ModelConfig& config, host::SampleMode mode, Rng* rng,
                               bool want_observability) {
  std::vector<Point> without_reflectance;
  if (!config.reflectance) {
    without_reflectance = scan_points;
    for (Point& p : without_reflectance) p.r = 0.0f;
  }
  const std::vector<Point>& points = config.reflectance ? scan_points : without_reflectance;
  ScanInputs in;
  const GridSpec& grid = config.grid;
  if (config.pillar_input) {
    const host::PillarConfig pc{config.max_points_per_pillar, config.max_pillars};
    const host::Pillars pillars = host::pillar_gather(points, grid, pc, mode, rng);
    in.pillar_points = host::decorate_points(points, pillars, grid);
    in.pillar_cells = pillars.cell;
  }
  const bool need_2d = config.occupancy == OccupancyInput::Observability2D ||
                       config.grid_map_input || want_observability;
  if (need_2d) {
    const host::ObservabilityCounts counts = host::observability_2d(points, origin, grid);
    in.observability = host::observability_map(counts);
    if (config.occupancy == OccupancyInput::Observability2D)
      in.occupancy = observability_input(in.observability);
    if (config.grid_map_input)
      in.grid_map = host::grid_map_features(points, counts.detections, counts.transmissions, grid);
  }
  if (config.occupancy == OccupancyInput::Occupancy3D)
    in.occupancy = host::occupancy_probability(host::occupancy_counts_3d(points, origin, grid));
  return in;
}

Tensor<float> observability_input(const Tensor<uint32_t>& observability) {
  PS_CHECK(observability.rank() == 2, "observability_input: expected (H, W), got {}",
           shape_str(observability.shape()));
  Tensor<float> out({1, observability.dim(0), observability.dim(1)});
  for (int64_t i = 0; i < observability.numel(); ++i)
    out[i] = static_cast<float>(std::log1p(static_cast<double>(observability[i])));
  return out;
}

ModelBatch collate(const std::vector<const ScanInputs*>& scans, const ModelConfig& config) {
  PS_CHECK(!scans.empty(), "collate: no scans");
  ModelBatch batch;
  const int64_t B = static_cast<int64_t>(scans.size());
  batch.batch = static_cast<int>(B);
  const int64_t H = config.grid.height(), W = config.grid.width(), N = config.max_points_per_pillar;
  if (config.pillar_input) {
    int64_t total = 0;
    for (const ScanInputs* s : scans)
      total += s->pillar_cells.rank() == 2 ? s->pillar_cells.dim(0) : 0;
    batch.pillar_points = Tensor<float>({total, N, 10});
    batch.pillar_cells = Tensor<int32_t>({total, 3});
    int64_t offset = 0;
    for (int64_t b = 0; b < B; ++b) {
      const ScanInputs& s = *scans[static_cast<size_t>(b)];
      const int64_t P = s.pillar_cells.rank() == 2 ? s.pillar_cells.dim(0) : 0;
      if (P == 0) continue;
      std::memcpy(batch.pillar_points.data() + offset * N * 10, s.pillar_points.data(),
                  static_cast<size_t>(P * N * 10) * sizeof(float));
      for (int64_t p = 0; p < P; ++p) {
        batch.pillar_cells(offset + p, 0) = static_cast<int32_t>(b);
        batch.pillar_cells(offset + p, 1) = s.pillar_cells(p, 0);
        batch.pillar_cells(offset + p, 2) = s.pillar_cells(p, 1);
      }
      offset += P;
    }
  }
  const auto stack = [&](auto member, int64_t channels) {
    Tensor<float> out({B, channels, H, W});
    const int64_t per = channels * H * W;
    for (int64_t b = 0; b < B; ++b) {
      const Tensor<float>& t = scans[static_cast<size_t>(b)]->*member;
      PS_CHECK(t.numel() == per,
               "collate: sample {} has an input map of shape {}, expected ({}, {}, {})", b,
               shape_str(t.shape()), channels, H, W);
      std::memcpy(out.data() + b * per, t.data(), static_cast<size_t>(per) * sizeof(float));
    }
    return out;
  };
  if (config.occupancy != OccupancyInput::None)
    batch.occupancy = stack(&ScanInputs::occupancy, config.occupancy_input_channels());
  if (config.grid_map_input) batch.grid_map = stack(&ScanInputs::grid_map, host::kGridMapLayers);
  return batch;
}

ModelBatch collate(ScanInputs&& scan, const ModelConfig& config) {
  ModelBatch batch;
  const int64_t H = config.grid.height(), W = config.grid.width(), N = config.max_points_per_pillar;
  if (config.pillar_input) {
    const int64_t P = scan.pillar_cells.rank() == 2 ? scan.pillar_cells.dim(0) : 0;
    PS_CHECK(
        scan.pillar_points.numel() == P * N * 10,
        "collate: the scan has {} pillars but pillar points of shape {}, expected ({}, {}, 10)", P,
        shape_str(scan.pillar_points.shape()), P, N);
    batch.pillar_points = std::move(scan.pillar_points);
    batch.pillar_points.reshape({P, N, 10});
    batch.pillar_cells = Tensor<int32_t>({P, 3});
    for (int64_t p = 0; p < P; ++p) {
      batch.pillar_cells(p, 0) = 0;
      batch.pillar_cells(p, 1) = scan.pillar_cells(p, 0);
      batch.pillar_cells(p, 2) = scan.pillar_cells(p, 1);
    }
  }
  const auto take = [&](Tensor<float>& t, int64_t channels) {
    PS_CHECK(t.numel() == channels * H * W,
             "collate: the scan has an input map of shape {}, expected ({}, {}, {})",
             shape_str(t.shape()), channels, H, W);
    Tensor<float> out = std::move(t);
    out.reshape({1, channels, H, W});
    return out;
  };
  if (config.occupancy != OccupancyInput::None)
    batch.occupancy = take(scan.occupancy, config.occupancy_input_channels());
  if (config.grid_map_input) batch.grid_map = take(scan.grid_map, host::kGridMapLayers);
  return batch;
}

}  // namespace pillarseg
