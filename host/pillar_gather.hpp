// Pillar gather (PointPillars / OpenPCDet semantics, DESIGN.md section 1 "Pillars"): groups the
// points of one scan that lie inside the grid volume into pillars (xy cells of the grid),
// numbered in order of first appearance in the file, keeps at most N points per pillar and at
// most P pillars. Output, for P' kept pillars: cell (P', 2) = (iy, ix), point_index (P', N) =
// indices into the input of the kept points in file order (padding -1), count (P').
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include "core/grid.hpp"
#include "core/point.hpp"
#include "core/rng.hpp"
#include "core/tensor.hpp"

namespace pillarseg::host {

struct PillarConfig {
  int max_points_per_pillar = 20;  // N, >= 1
  int max_pillars = 0;             // P; 0 keeps every non-empty pillar
};

// Inference subsamples at evenly spaced positions (deterministic); Training draws a seeded
// uniform random subset.
enum class SampleMode { Inference, Training };

struct Pillars {
  Tensor<int32_t> cell;         // (P', 2): iy, ix
  Tensor<int32_t> point_index;  // (P', N): input indices of the kept points in file order; -1 pads
  Tensor<int32_t> count;        // (P'): number of kept points, 1..N

  int64_t num_pillars() const { return count.numel(); }
  int64_t max_points_per_pillar() const { return point_index.rank() == 2 ? point_index.dim(1) : 0; }
};

// Positions of the `keep` items kept out of `n` (keep <= n), ascending, written to out[0..keep):
// Inference: floor(k * n / keep) for k = 0..keep-1; Training: a uniform random subset drawn
// from `rng` (selection sampling, Knuth's Algorithm S, which yields them in order).
void select_positions(int64_t n, int64_t keep, SampleMode mode, Rng* rng, int32_t* out);

// Scratch memory of pillar_gather, reusable across scans: the W * H cell -> pillar map (kept
// all -1 between calls, so it is filled once, not per scan) and per-point / per-pillar lists.
// One workspace per thread; a steady-state loop that keeps it (and the output) allocates
// nothing once the buffers have grown.
struct PillarWorkspace {
  std::vector<int32_t> pillar_of_cell;    // (W * H): pillar of a cell or -1
  bool cell_map_clean = false;            // pillar_of_cell is all -1 and sized for the grid
  std::vector<int32_t> pillar_of_point;   // (M): pillar of a point or -1 outside the volume
  std::vector<int32_t> pillar_flat_cell;  // (>= #non-empty): iy * W + ix, per pillar id
  std::vector<int32_t> pillar_size;       // (>= #non-empty): points before subsampling
  std::vector<int32_t> pillar_begin;      // (#non-empty + 1): CSR offsets into members
  std::vector<int32_t> cursor;            // (#non-empty): fill position while sorting
  std::vector<int32_t> members;           // (#inside + N): point indices grouped by pillar
  std::vector<int32_t> kept_pillars;      // (P')
  std::vector<int32_t> positions;         // (N)
};

// points: M points of one scan (LiDAR frame). Only points with grid.contains(x, y, z) are used.
// Returns P' = min(#non-empty pillars, P) pillars (all of them when P = 0), in first-appearance
// order; a pillar with n > N points keeps N of them, chosen by select_positions. In Training
// the pillar subset is drawn first, then the point subsets pillar by pillar, all from `rng`
// (required in Training, unused in Inference). O(M) time with a warm workspace.
Pillars pillar_gather(std::span<const Point> points, const GridSpec& grid,
                      const PillarConfig& cfg, SampleMode mode, Rng* rng);

// Same, with caller-owned scratch and output: `out` is overwritten and its tensors keep their
// allocations when large enough.
void pillar_gather(std::span<const Point> points, const GridSpec& grid, const PillarConfig& cfg,
                   SampleMode mode, Rng* rng, PillarWorkspace& workspace, Pillars& out);

// Caller memory for up to `capacity` pillars: cell (capacity, 2), point_index (capacity, N),
// count (capacity).
struct PillarRows {
  int32_t* cell = nullptr;
  int32_t* point_index = nullptr;
  int32_t* count = nullptr;
  int64_t capacity = 0;
};

// Same, into `out`: rows 0..P'-1 as above (rows past P' are not written); returns P'. More than
// `capacity` pillars is an error naming both counts.
int64_t pillar_gather(std::span<const Point> points, const GridSpec& grid, const PillarConfig& cfg,
                      SampleMode mode, Rng* rng, PillarWorkspace& workspace,
                      const PillarRows& out);

}  // namespace pillarseg::host
