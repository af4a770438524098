// Scene geometry of the simulator: primitives (boxes and ellipsoids turned about the vertical
// axis, vertical cylinders), each with a SemanticKITTI label, an albedo and a surface kind;
// ray-primitive intersection; and SceneGrid, a 2D uniform grid over the primitives' footprints
// that a ray walks cell by cell (Amanatides & Woo), so that it tests only the primitives whose
// footprint it crosses and stops at the first cell that ends behind its nearest hit.
// Units are metres; the world frame has z up.
#pragma once

#include <cstdint>
#include <vector>

#include "core/eigen.hpp"

namespace pillarseg::sim {

enum class Shape : uint8_t { kBox, kCylinder, kEllipsoid };

// How a surface answers a laser pulse (lidar.cpp): kSolid returns at the surface; kFoliage
// returns inside the volume after a random free path, or lets the pulse through when the path
// is longer than the volume; kMesh (wire fences, spoked wheels) lets a share of pulses pass;
// kGlass (car windows) loses a share of pulses and lets some pass.
enum class Surface : uint8_t { kSolid, kFoliage, kMesh, kGlass };

struct Primitive {
  Shape shape = Shape::kBox;
  Surface surface = Surface::kSolid;
  float albedo = 0.2f;  // reflectance at normal incidence, in [0, 1]
  uint32_t label = 0;   // raw SemanticKITTI word: instance << 16 | semantic id
  Eigen::Vector3d center = Eigen::Vector3d::Zero();
  // Half sizes (box) or radii (ellipsoid) along the local x, y, z axes; a cylinder's is
  // (radius, radius, half height).
  Eigen::Vector3d half = Eigen::Vector3d::Ones();
  double cos_yaw = 1.0, sin_yaw = 0.0;  // the local x axis is (cos_yaw, sin_yaw, 0) in the world
};

Primitive make_box(const Eigen::Vector3d& center, const Eigen::Vector3d& half, double yaw,
                   uint32_t label, float albedo, Surface surface = Surface::kSolid);
// A vertical cylinder over the disc of the given radius around (x, y), from z0 to z1.
Primitive make_cylinder(double x, double y, double z0, double z1, double radius, uint32_t label,
                        float albedo, Surface surface = Surface::kSolid);
Primitive make_ellipsoid(const Eigen::Vector3d& center, const Eigen::Vector3d& radii, double yaw,
                         uint32_t label, float albedo, Surface surface = Surface::kSolid);

struct Ray {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  Eigen::Vector3d dir = Eigen::Vector3d::UnitX();  // unit length
};

struct Hit {
  double t_enter = 0, t_exit = 0;  // where the ray enters and leaves the primitive
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();  // outward unit normal at the entry point
  int32_t primitive = -1;                             // index into the scene's primitives
};

// The ray's entry into the primitive when t_enter lies in [t_min, t_max]. A ray that starts
// inside the primitive (t_enter < t_min < t_exit) does not hit it. hit->primitive is not set.
bool intersect(const Primitive& primitive, const Ray& ray, double t_min, double t_max, Hit* hit);

// Axis-aligned bounding box of the primitive's footprint in xy, and its lowest and highest z.
struct Footprint {
  double x0, y0, x1, y1, z0, z1;
};
Footprint footprint(const Primitive& primitive);

// Nearest entry over all primitives by testing every one: the reference SceneGrid is checked
// against.
bool trace_brute_force(const std::vector<Primitive>& primitives, const Ray& ray, double t_min,
                       double t_max, Hit* hit);

class SceneGrid {
 public:
  SceneGrid() = default;
  // Grid of square cells of cell_size metres over the footprints of all primitives.
  SceneGrid(std::vector<Primitive> primitives, double cell_size);

  // Nearest entry with t_enter in [t_min, t_max]; equal to trace_brute_force's (ties between
  // primitives entered at the same t may pick either).
  bool trace(const Ray& ray, double t_min, double t_max, Hit* hit) const;

  const std::vector<Primitive>& primitives() const { return primitives_; }
  size_t size() const { return primitives_.size(); }
  int cells_x() const { return nx_; }
  int cells_y() const { return ny_; }

 private:
  std::vector<Primitive> primitives_;
  double cell_ = 1.0, x0_ = 0.0, y0_ = 0.0;
  int nx_ = 0, ny_ = 0;
  std::vector<int64_t>
      cell_begin_;  // nx * ny + 1 offsets into cell_items_ (CSR), row iy, column ix
  std::vector<int32_t> cell_items_;  // primitive indices, ascending within a cell
  std::vector<double>
      cell_top_;  // highest z of the cell's primitives (skips cells a ray passes over)
};

}  // namespace pillarseg::sim
