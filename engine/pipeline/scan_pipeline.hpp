// ScanPipeline: a scan's raw points -> the network's inputs, as backend ops (DESIGN.md section 6):
// the CPU backend runs host/, the CUDA backend the kernels, on the backend's own memory.
//
//   points (M, 4) --pillar gather--> cell (R, 2), point_index (R, N), count (R)
//                 --decoration-----> the model's pillar_points (rows, N, 10)
//                 --batch cells----> the model's pillar_cells (rows, 3) (sample, iy, ix)
//                 --2D ray walks---> transmissions, detections (H, W)
//                                    --> the occupancy input log(1 + t + d) or the grid-map layers
//                 --3D ray walks---> the occupancy input (Z, H, W)
//
// The pipeline owns the point buffer (capacity, 4), the gather's outputs and the ray counts; it
// writes the network's inputs where PillarSegNet::prepare() planned them. Two ways to run it:
// - on the backend's own gather, inference sampling (gather_pillars(), then fill()): what
//   inference does, on any backend;
// - on pillars gathered on the host (upload_pillars(), then fill()): what training does, whose
//   seeded random subsets are drawn in one sequence on the host; decoration and the maps still
//   run on the backend.
// Where the backend records graphs, a scan of any size up to the capacity runs in one recording:
// the points past the scan are padded with NaN (pad_points), which no op counts, and the gather
// writes R = pillar_rows(capacity) rows, inert past the scan's P'.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "core/eigen.hpp"
#include "core/point.hpp"
#include "engine/backend/backend.hpp"
#include "engine/model/config.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "host/pillar_gather.hpp"

namespace pillarseg {

class ScanPipeline {
 public:
  // ray_counts: compute the 2D ray counts for every scan, also when the model reads none (to mask
  // unobserved cells).
  ScanPipeline(const ModelConfig& config, Backend& backend, bool ray_counts = false);

  // Buffers for scans of up to `points` points (they grow with headroom, never shrink); true when
  // they moved, which invalidates anything recorded on them. Throws pillarseg::Error, before
  // allocating, for more points than the 32-bit point indices hold or the backend's memory
  // (Backend::memory_budget()) takes; the buffers are then released (capacity() -1).
  bool reserve(int64_t points);
  int64_t capacity() const { return capacity_; }
  // Changes whenever the buffers move (or are released), so that a recording on them is stale.
  int64_t buffer_generation() const { return buffer_generation_; }
  // R for the capacity: the gather's rows.
  int64_t gather_rows() const { return gather_rows_; }

  // Reserves room for the scan, copies its points into the point buffer and its count into
  // num_points; returns the points as (M, 4) on the backend. On the CPU backend no copy is
  // needed: `points` is returned as it is (host memory, valid while the caller's are). A model
  // without reflectance (ModelConfig::reflectance false) gets a copy with every r = 0.
  Ref load_points(std::span<const Point> points);
  // The whole point buffer (capacity, 4) and the count (1), for a recorded pipeline.
  Ref point_buffer() const { return points_; }
  IRef num_points() const { return num_points_; }

  // Queues pad_points on the whole buffer: rows past num_points become NaN.
  void pad_points();
  // Queues the gather (inference sampling) of `points` ((m, 4), m <= capacity); returns the rows
  // the next ops must read (P' on the CPU backend, R(m) on the CUDA backend).
  int64_t gather_pillars(const Ref& points);
  // The gather's P' (1), in the backend's memory.
  const IRef& gathered_pillars() const { return num_pillars_; }
  // Copies pillars gathered on the host (P' <= R rows) into the gather's outputs; returns P'.
  int64_t upload_pillars(const host::Pillars& pillars);
  // After gather_pillars(): P' (1) in the backend's memory, which the decoration (fill_pillars)
  // and the evaluation PFN (PillarSegNet::set_live_pillar_rows) read so that they stop at the
  // scan's own pillars, not at the R rows planned; after upload_pillars(): empty (every row
  // given is a pillar).
  IRef live_pillar_rows() const { return gathered_ ? num_pillars_ : IRef{}; }

  // Queues the decoration and the cells of the first `rows` gathered rows of the scan in `points`
  // into sample `sample` of `inputs`, its pillar rows from `row_offset`.
  void fill_pillars(const Ref& points, int64_t rows, int sample, int64_t row_offset,
                    const PillarSegNet::Inputs& inputs);
  // Queues the ray walks and the input maps of the scan (sensor at `origin`) into plane `sample`
  // of the inputs' occupancy and grid-map tensors.
  void fill_maps(const Ref& points, const Eigen::Vector3d& origin, int sample,
                 const PillarSegNet::Inputs& inputs);

  // The last fill_maps()'s ray counts (H, W): for masking unobserved cells.
  const URef& transmissions() const { return transmissions_; }
  const URef& detections() const { return detections_; }
  bool has_ray_counts() const { return needs_ray_counts_; }

 private:
  ModelConfig config_;
  Backend& backend_;
  bool needs_ray_counts_;
  int64_t capacity_ = -1, gather_rows_ = 0;
  int64_t buffer_generation_ = 0;
  bool gathered_ = false;  // the gather's rows came from gather_pillars(), not upload_pillars()
  std::unique_ptr<Arena> arena_;
  Ref points_;
  std::vector<Point> without_reflectance_;  // the scan's points with r = 0, when the model has none
  IRef num_points_, cell_, point_index_, count_, num_pillars_;
  URef transmissions_, detections_;
};

}  // namespace pillarseg
