#include "engine/pipeline/scan_pipeline.hpp"

#include <algorithm>
#include <cstring>

#include "core/error.hpp"
#include "core/memory_budget.hpp"

namespace pillarseg {

namespace {

// Rows [offset, offset + rows) and the leading `rows` rows of a tensor (backend.hpp's row_slice).
template <class T>
RefT<T> row_slice(const RefT<T>& whole, int64_t offset, int64_t rows) {
  return row_slice("scan pipeline", whole, offset, rows);
}
template <class T>
RefT<T> leading(const RefT<T>& whole, int64_t rows) {
  return row_slice(whole, 0, rows);
}

// Plane `sample` of a (B, C, H, W) input: (C, H, W).
Ref sample_plane(const Ref& batch, int sample) {
  const Shape plane{batch.dim(1), batch.dim(2), batch.dim(3)};
  return Ref{batch.data + int64_t{sample} * shape_numel(plane), plane};
}

}  // namespace

ScanPipeline::ScanPipeline(const ModelConfig& config, Backend& backend, bool ray_counts)
    : config_(config),
      backend_(backend),
      needs_ray_counts_(ray_counts || config.occupancy == OccupancyInput::Observability2D ||
                        config.grid_map_input),
      arena_(std::make_unique<Arena>(backend)) {}

bool ScanPipeline::reserve(int64_t points) {
  PS_CHECK(points >= 0, "scan pipeline: a scan has >= 0 points, given {}", points);
  if (points <= capacity_) return false;
  // Point indices are int32 in every op (the gather keeps kMaxInt32Index itself out of range).
  PS_CHECK(points < kMaxInt32Index, "a scan of {} points overflows the 32-bit point indices (at most {} points)",
           points, kMaxInt32Index - 1);
  // Headroom so that scans growing by a few points do not re-plan (and record) every time.
  const int64_t capacity = std::min(std::max<int64_t>(points + points / 4, 4096), kMaxInt32Index - 1);
  const GridSpec& grid = config_.grid;
  const int64_t rows = config_.pillar_input ? pillar_rows(capacity, grid, config_.max_pillars) : 0;
  const int64_t N = config_.max_points_per_pillar;
  Arena& a = *arena_;
  a.release();
  capacity_ = -1, gather_rows_ = 0;  // nothing is reserved until this call completes
  ++buffer_generation_;
  a.begin_measure();
  for (int pass = 0; pass < 2; ++pass) {
    if (pass == 1) {
      // The buffers, and the gather's working memory in the backend (about 8 int32 a point and
      // 2 a cell, kernels/pillar_gather.cuh).
      const uint64_t workspace = checked_product({4, 8 * capacity + 2 * grid.cells()}, "the gather's workspace");
      require_memory(checked_sum({a.used(), workspace}, "the scan buffers"),
                     fmt::format("a scan of {} points (buffers for {} points, {} pillar rows)", points, capacity, rows),
                     backend_.memory_budget());
      a.reserve(a.used());
      a.reset();
    }
    points_ = a.take<float>({capacity, 4});
    num_points_ = a.take<int32_t>({1});
    cell_ = a.take<int32_t>({rows, 2});
    point_index_ = a.take<int32_t>({rows, N});
    count_ = a.take<int32_t>({rows});
    num_pillars_ = a.take<int32_t>({1});
    if (needs_ray_counts_) {
      transmissions_ = a.take<uint32_t>({grid.height(), grid.width()});
      detections_ = a.take<uint32_t>({grid.height(), grid.width()});
    }
  }
  capacity_ = capacity;
  gather_rows_ = rows;
  return true;
}

Ref ScanPipeline::load_points(std::span<const Point> scan_points) {
  std::span<const Point> points = scan_points;
  if (!config_.reflectance) {
    without_reflectance_.assign(scan_points.begin(), scan_points.end());
    for (Point& p : without_reflectance_) p.r = 0.0f;
    points = without_reflectance_;
  }
  const auto m = static_cast<int64_t>(points.size());
  reserve(m);
  if (backend_.device() == Device::Cpu) {
    // Host memory already: the ops read the caller's points.
    return Ref{const_cast<float*>(reinterpret_cast<const float*>(points.data())), {m, 4}};
  }
  if (m > 0) backend_.upload(points_.data, points.data(), points.size_bytes());
  const auto count = static_cast<int32_t>(m);
  backend_.upload(num_points_.data, &count, sizeof count);
  return leading(points_, m);
}

void ScanPipeline::pad_points() {
  PS_CHECK(capacity_ >= 0, "scan pipeline: reserve() before pad_points()");
  backend_.pad_points(num_points_, points_);
}

int64_t ScanPipeline::gather_pillars(const Ref& points) {
  if (!config_.pillar_input) return 0;
  PS_CHECK(points.dim(0) <= capacity_, "scan pipeline: {} points, room for {} (load_points() first)",
           points.dim(0), capacity_);
  const int64_t rows = pillar_rows(points.dim(0), config_.grid, config_.max_pillars);
  IRef cell = leading(cell_, rows), point_index = leading(point_index_, rows),
       count = leading(count_, rows);
  gathered_ = true;
  return backend_.pillar_gather(points, config_.grid, config_.max_pillars, cell, point_index, count,
                                num_pillars_);
}

int64_t ScanPipeline::upload_pillars(const host::Pillars& pillars) {
  const int64_t P = pillars.num_pillars();
  PS_CHECK(pillars.max_points_per_pillar() == config_.max_points_per_pillar || P == 0,
           "scan pipeline: pillars of {} slots, the model has N = {}", pillars.max_points_per_pillar(),
           config_.max_points_per_pillar);
  PS_CHECK(P <= gather_rows_, "scan pipeline: {} host pillars, room for {} (reserve() the scan first)", P,
           gather_rows_);
  gathered_ = false;
  if (P == 0) return 0;
  backend_.upload(cell_.data, pillars.cell.data(), static_cast<size_t>(pillars.cell.numel()) * sizeof(int32_t));
  backend_.upload(point_index_.data, pillars.point_index.data(),
                  static_cast<size_t>(pillars.point_index.numel()) * sizeof(int32_t));
  backend_.upload(count_.data, pillars.count.data(), static_cast<size_t>(P) * sizeof(int32_t));
  return P;
}

void ScanPipeline::fill_pillars(const Ref& points, int64_t rows, int sample, int64_t row_offset,
                                const PillarSegNet::Inputs& inputs) {
  const GridSpec& grid = config_.grid;
  if (config_.pillar_input && rows > 0) {
    Ref decorated = row_slice(inputs.pillar_points, row_offset, rows);
    IRef cells = row_slice(inputs.pillar_cells, row_offset, rows);
    const IRef cell = leading(cell_, rows);
    backend_.decorate_points(points, grid, cell, leading(point_index_, rows), leading(count_, rows),
                             live_pillar_rows(), decorated);
    backend_.batch_cells(cell, sample, cells);
  }
}

void ScanPipeline::fill_maps(const Ref& points, const Eigen::Vector3d& origin, int sample,
                             const PillarSegNet::Inputs& inputs) {
  const GridSpec& grid = config_.grid;
  if (needs_ray_counts_) backend_.observability_2d(points, origin, grid, transmissions_, detections_);
  if (config_.occupancy == OccupancyInput::Observability2D) {
    Ref plane = sample_plane(inputs.occupancy, sample);
    backend_.observability_input(transmissions_, detections_, plane);
  }
  if (config_.occupancy == OccupancyInput::Occupancy3D) {
    Ref plane = sample_plane(inputs.occupancy, sample);
    backend_.occupancy_3d(points, origin, grid, plane);
  }
  if (config_.grid_map_input) {
    Ref plane = sample_plane(inputs.grid_map, sample);
    backend_.grid_map_features(points, grid, detections_, transmissions_, plane);
  }
}

}  // namespace pillarseg
