// City: the procedural street world of one simulated sequence.
//
// A main street (straight stretches and curves) holds the ego vehicle's drive; side streets
// leave it every 55-100 m. Each street has a cross-section per side, from the centre line out:
// driving lanes | bike lane | parking strip | curb | tree lawn | sidewalk | front yards |
// building line | backyards. The ground is not made of primitives: ground_at(x, y) evaluates
// this layout at a point (SemanticKITTI label, albedo, height, and whether the surface is on the
// raised side of a curb), a height field that the LiDAR model marches along each pulse. The
// height is not flat (Relief): long waves give the streets grades, shorter ones hills and
// embankments away from the streets, roads have a camber down from the centre line, curbs
// (10-16 cm) raise sidewalks and lawns, sidewalks slope up from the curb, and terrain is bumpy.
// Lots along each side hold buildings or gaps with fences, hedges and yards; street furniture,
// trees, parked vehicles, bicycles and standing people are static primitives in one SceneGrid.
// Moving agents (traffic, cyclists, walkers) follow routes along the streets at constant speed and
// are posed per time. World frame: x, y horizontal, z up, z = 0 the mean road level. Units: metres,
// seconds.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <utility>
#include <vector>

#include "core/eigen.hpp"
#include "engine/sim/objects.hpp"
#include "engine/sim/scene.hpp"

namespace pillarseg::sim {

inline constexpr double kScanPeriod = 0.1;     // s between scans (10 Hz)
inline constexpr double kSensorHeight = 1.73;  // LiDAR above the road, m

// Bands of a street's cross-section, from the centre line outwards.
enum class Zone : uint8_t { kRoad, kBikeLane, kParking, kLawn, kSidewalk, kFront, kBack, kOutside };

// A stretch of a street side between two neighbours' boundaries.
struct Lot {
  double s0 = 0, s1 = 0;  // arc-length interval
  bool building = false;
  // A lot without a building at the building line may be an open green: no fence or hedge at
  // the sidewalk, grass to the back (the real scans' far buildings stand behind open grass).
  bool open_green = false;
  double far_setback = 0;  // > 0: a building this far behind the building line (open greens)
  uint32_t front_label = raw::kTerrain;  // ground of the front yard
  uint32_t back_label = raw::kTerrain;   // ground behind the building line
  // A paved path (sidewalk) from the back of the sidewalk into the yard, at the yard's level:
  // centred on arc length path_s, path_half wide to each side, path_depth deep (0: none).
  double path_s = 0, path_half = 0, path_depth = 0;
  bool on_path(double s, double depth) const {
    return path_depth > 0 && std::abs(s - path_s) < path_half && depth < path_depth;
  }
};

struct StreetSide {
  double bike = 0, parking = 0, lawn = 0, sidewalk = 2, front = 0;  // band widths
  // Height of the yards relative to the sidewalk's back edge, where they meet it (grass flush
  // with the paving, give or take a few centimetres; the tree lawn the same).
  double terrain_offset = 0;
  // Beyond the sidewalk the yards fall away (yard_drop > 0) or rise (< 0) by up to
  // |yard_drop| m, at yard_slope where they meet the sidewalk and levelling off further out
  // (t m behind the sidewalk: -yard_drop (1 - exp(-yard_slope t / |yard_drop|))), back to the
  // sidewalk's level over the backyards' last kYardLevel m. In the real labelled scan the grass
  // lies at the paving's level up to 3 m behind the sidewalk, 0.12 m below it 3-6 m out and
  // 0.24 m below 6-12 m out (medians).
  double yard_drop = 0, yard_slope = 0.03;
  static constexpr double kYardLevel = 12.0;
  // The yards' height relative to the sidewalk's back edge at distance a from the centre line
  // (a >= e_walk).
  double yard_offset(double a) const;
  // Outer edge of each band, distance from the centre line.
  double e_road = 0, e_bike = 0, e_curb = 0, e_lawn = 0, e_walk = 0, e_front = 0, e_back = 0;
  std::vector<double> stretch_end;       // parking stretches: arc length where each ends, ascending
  std::vector<uint8_t> stretch_parking;  // 1: marked parking (raw 44), 0: plain road surface
  std::vector<Lot> lots;                 // ascending, covering [0, length]
  void set_edges(double road_half_width, double backyard);
};

// A point of a street's centre line with its unit tangent and unit normal (left of the tangent).
struct StreetFrame {
  Eigen::Vector2d p, tangent, normal;
};

struct Street {
  std::vector<Eigen::Vector2d> points;  // centre-line polyline
  std::vector<double> arc;              // arc length at each vertex
  int lanes = 1;                        // driving lanes per direction
  double lane_width = 3.25;
  // [0]: right of the direction of increasing s (offset d < 0), [1]: left (d > 0).
  std::array<StreetSide, 2> sides;
  std::vector<std::pair<double, double>> crosswalks;  // arc-length intervals with zebra stripes
  float road_albedo = 0.18f;

  explicit Street(std::vector<Eigen::Vector2d> polyline);
  double length() const { return arc.back(); }
  int segments() const { return static_cast<int>(points.size()) - 1; }
  // Frame at arc length s (clamped to [0, length]); the tangent is interpolated between segment
  // midpoints so that offset paths are smooth.
  StreetFrame at(double s) const;
  // World point at arc length s and signed lateral offset d.
  Eigen::Vector2d point(double s, double d) const;
  // Arc length s and signed offset d of q, searching from segment hint along the polyline.
  // Beyond the ends s is extrapolated (s < 0 or s > length). Returns the nearest segment.
  int project(const Eigen::Vector2d& q, int hint, double* s, double* d) const;
  Zone zone(double s, double d) const;
  const StreetSide& side_of(double d) const { return sides[d < 0 ? 0 : 1]; }
  // Segment k's vector points[k + 1] - points[k] and its squared length, for project().
  std::vector<Eigen::Vector2d> segment_vector;
  std::vector<double> segment_length2;
};

// Where a point lies relative to one street.
struct StreetCoord {
  int street = 0;
  double s = 0, d = 0;  // arc length and signed lateral offset
  Zone zone = Zone::kOutside;
};

// What the ground is at a point.
struct GroundSample {
  uint32_t label = raw::kTerrain;
  float albedo = 0.4f;
  bool raised = true;  // on the curb's upper side (sidewalk, lawn, yards) rather than the road's
  double z = 0;        // height of the surface
};

// The smooth part of the ground's height: plane waves a sin(k . p + phase).
struct Relief {
  struct Wave {
    double kx = 0, ky = 0, amplitude = 0, phase = 0;
  };
  std::vector<Wave> grade;    // long waves everywhere: the streets' grades (a few per cent)
  std::vector<Wave> hills;    // shorter waves beyond the sidewalks (faded in over kHillFade m)
  double camber = 0.02;       // the road's cross slope, down from the centre line
  double walk_slope = 0.015;  // sidewalks and lawns rise away from the curb
  double roughness = 0.04;    // amplitude of the terrain's bumps, m
  // The largest slope of the smooth part (grades, hills, camber, bumps): the LiDAR's march
  // along a pulse steps by the gap over this bound.
  static constexpr double kMaxSlope = 0.2;
  static constexpr double kHillFade = 20.0;  // m beyond the sidewalk over which hills fade in
  double grade_at(double x, double y) const;
  double hills_at(double x, double y) const;
};

// A moving agent's way: along one street between s0 and s1.
struct Route {
  enum class Kind : uint8_t {
    kLoopForward,   // towards +s, from s1 back to s0 (far from the ego)
    kLoopBackward,  // towards -s
    kShuttle,       // out towards +s at offset_out, back towards -s at offset_back
    kFollowEgo      // the ego's lane at the ego's speed, u0 metres ahead (negative: behind)
  };
  Kind kind = Kind::kLoopForward;
  int street = 0;
  double s0 = 0, s1 = 0;
  double offset_out = 0, offset_back = 0;  // signed lateral offsets
};

struct MovingAgent {
  Agent agent;
  Route route;
  double u0 = 0;     // position along the route at t = 0, metres
  double speed = 0;  // m/s along the route
};

// The ego vehicle's drive: arc length s(t) = s0 + v0 t + (a / w)(1 - cos w t) on the main street.
struct EgoDrive {
  double s0 = 0, v0 = 8, accel_amp = 0, omega = 0.5;
  double lane_offset = -1.6;            // signed offset of the lane centre
  double sway = 0.1, sway_omega = 0.3;  // lateral sway amplitude (m) and angular rate
  double pitch_amp = 0, roll_amp = 0;   // radians
  double s(double t) const;
  double speed(double t) const;
};

class City {
 public:
  // A city whose main street holds the ego's drive of `scans` scans with 170 m of street before
  // and after it. Deterministic in seed.
  static City generate(uint64_t seed, int scans);

  GroundSample ground_at(double x, double y) const;
  // The streets near (x, y) (at most 8, ascending street index) with the point's coordinates
  // along each; returns how many were written.
  int locate(double x, double y, std::array<StreetCoord, 8>* out) const;
  double curb_height() const { return curb_height_; }
  const Relief& relief() const { return relief_; }
  // Height of the ground surface at (x, y).
  double ground_z(double x, double y) const { return ground_at(x, y).z; }

  const std::vector<Street>& streets() const { return streets_; }
  const SceneGrid& static_scene() const { return static_scene_; }
  const std::vector<MovingAgent>& movers() const { return movers_; }
  const EgoDrive& ego() const { return ego_; }

  // Pose of a moving agent at time t; *travelled (optional) is its distance along the route.
  Placement mover_pose(const MovingAgent& mover, double t, double* travelled = nullptr) const;
  // Appends the primitives of the moving agents at time t whose base lies within radius of center.
  void moving_primitives(double t, const Eigen::Vector2d& center, double radius,
                         std::vector<Primitive>& out) const;
  // LiDAR-to-world transform (4x4) of the ego's sensor at time t.
  Eigen::Matrix4d lidar_pose(double t) const;

 private:
  struct IndexEntry {
    int32_t street, segment;
  };
  void build_ground_index();

  std::vector<Street> streets_;  // [0] is the main street
  std::vector<double>
      side_angle_;  // per street: angle between a side street and the main street's normal
  double curb_height_ = 0.12;
  Relief relief_;
  uint32_t texture_salt_ = 0;  // varies the ground's texture and bumps between cities
  // Per-city means of the ground materials' albedo (road, sidewalk, lawns' and yards' terrain,
  // other ground).
  float road_albedo_ = 0.28f, walk_albedo_ = 0.42f, terrain_albedo_ = 0.47f,
        other_ground_albedo_ = 0.3f;
  EgoDrive ego_;
  SceneGrid static_scene_;
  std::vector<MovingAgent> movers_;
  // Ground index: square cells with, per cell, the streets near it and a segment to start
  // their projection from (CSR, row iy, column ix).
  double index_x0_ = 0, index_y0_ = 0, index_cell_ = 4.0;
  int index_nx_ = 0, index_ny_ = 0;
  std::vector<int64_t> index_begin_;
  std::vector<IndexEntry> index_entries_;

  friend class CityBuilder;
};

}  // namespace pillarseg::sim
