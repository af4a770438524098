#include "engine/sim/scene.hpp"

#include <algorithm>
#include <cmath>
#include <limits>

#include "core/error.hpp"

namespace pillarseg::sim {

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kTiny = 1e-12;

// The ray in the primitive's local frame: centre at the origin, local x axis along +x.
void to_local(const Primitive& p, const Ray& ray, Eigen::Vector3d* o, Eigen::Vector3d* d) {
  const Eigen::Vector3d rel = ray.origin - p.center;
  *o = {p.cos_yaw * rel.x() + p.sin_yaw * rel.y(), -p.sin_yaw * rel.x() + p.cos_yaw * rel.y(),
        rel.z()};
  *d = {p.cos_yaw * ray.dir.x() + p.sin_yaw * ray.dir.y(),
        -p.sin_yaw * ray.dir.x() + p.cos_yaw * ray.dir.y(), ray.dir.z()};
}

Eigen::Vector3d to_world_dir(const Primitive& p, const Eigen::Vector3d& v) {
  return {p.cos_yaw * v.x() - p.sin_yaw * v.y(), p.sin_yaw * v.x() + p.cos_yaw * v.y(), v.z()};
}

bool accept(double t_enter, double t_exit, double t_min, double t_max, Hit* hit) {
  if (t_enter > t_exit || t_enter < t_min || t_enter > t_max) return false;
  hit->t_enter = t_enter;
  hit->t_exit = t_exit;
  return true;
}

bool intersect_box(const Primitive& p, const Ray& ray, double t_min, double t_max, Hit* hit) {
  Eigen::Vector3d o, d;
  to_local(p, ray, &o, &d);
  double t_enter = -kInf, t_exit = kInf;
  int axis = -1;
  double sign = 1.0;
  for (int a = 0; a < 3; ++a) {
    if (std::abs(d[a]) < kTiny) {
      if (std::abs(o[a]) > p.half[a]) return false;
      continue;
    }
    const double inv = 1.0 / d[a];
    double ta = (-p.half[a] - o[a]) * inv, tb = (p.half[a] - o[a]) * inv;
    if (ta > tb) std::swap(ta, tb);
    if (ta > t_enter) {
      t_enter = ta;
      axis = a;
      sign = d[a] > 0 ? -1.0 : 1.0;  // the face the ray enters through faces against it
    }
    t_exit = std::min(t_exit, tb);
  }
  if (axis < 0 || !accept(t_enter, t_exit, t_min, t_max, hit)) return false;
  Eigen::Vector3d n = Eigen::Vector3d::Zero();
  n[axis] = sign;
  hit->normal = to_world_dir(p, n);
  return true;
}

bool intersect_cylinder(const Primitive& p, const Ray& ray, double t_min, double t_max, Hit* hit) {
  const double ox = ray.origin.x() - p.center.x(), oy = ray.origin.y() - p.center.y();
  const double dx = ray.dir.x(), dy = ray.dir.y();
  const double r = p.half.x();
  // Side: |o_xy + t d_xy| = r.
  double side_in = -kInf, side_out = kInf;
  const double a = dx * dx + dy * dy;
  const double c = ox * ox + oy * oy - r * r;
  if (a < kTiny) {
    if (c > 0) return false;
  } else {
    const double b = ox * dx + oy * dy;
    const double disc = b * b - a * c;
    if (disc < 0) return false;
    const double root = std::sqrt(disc);
    side_in = (-b - root) / a;
    side_out = (-b + root) / a;
  }
  // Caps: z in [center - half, center + half].
  double cap_in = -kInf, cap_out = kInf;
  const double oz = ray.origin.z() - p.center.z(), dz = ray.dir.z();
  if (std::abs(dz) < kTiny) {
    if (std::abs(oz) > p.half.z()) return false;
  } else {
    cap_in = (-p.half.z() - oz) / dz;
    cap_out = (p.half.z() - oz) / dz;
    if (cap_in > cap_out) std::swap(cap_in, cap_out);
  }
  const double t_enter = std::max(side_in, cap_in), t_exit = std::min(side_out, cap_out);
  if (!std::isfinite(t_enter) || !accept(t_enter, t_exit, t_min, t_max, hit)) return false;
  if (side_in >= cap_in) {
    hit->normal = Eigen::Vector3d((ox + t_enter * dx) / r, (oy + t_enter * dy) / r, 0.0);
  } else {
    hit->normal = Eigen::Vector3d(0, 0, dz > 0 ? -1.0 : 1.0);
  }
  return true;
}

bool intersect_ellipsoid(const Primitive& p, const Ray& ray, double t_min, double t_max, Hit* hit) {
  Eigen::Vector3d o, d;
  to_local(p, ray, &o, &d);
  // Scaling each axis by its radius maps the ellipsoid to the unit sphere and keeps t.
  const Eigen::Vector3d os = o.cwiseQuotient(p.half), ds = d.cwiseQuotient(p.half);
  const double a = ds.squaredNorm(), b = os.dot(ds), c = os.squaredNorm() - 1.0;
  const double disc = b * b - a * c;
  if (disc < 0 || a < kTiny) return false;
  const double root = std::sqrt(disc);
  const double t_enter = (-b - root) / a, t_exit = (-b + root) / a;
  if (!accept(t_enter, t_exit, t_min, t_max, hit)) return false;
  const Eigen::Vector3d local = o + t_enter * d;
  hit->normal = to_world_dir(p, local.cwiseQuotient(p.half.cwiseProduct(p.half))).normalized();
  return true;
}

}  // namespace

Primitive make_box(const Eigen::Vector3d& center, const Eigen::Vector3d& half, double yaw,
                   uint32_t label, float albedo, Surface surface) {
  Primitive p;
  p.shape = Shape::kBox;
  p.surface = surface;
  p.albedo = albedo;
  p.label = label;
  p.center = center;
  p.half = half;
  p.cos_yaw = std::cos(yaw);
  p.sin_yaw = std::sin(yaw);
  return p;
}

Primitive make_cylinder(double x, double y, double z0, double z1, double radius, uint32_t label,
                        float albedo, Surface surface) {
  Primitive p;
  p.shape = Shape::kCylinder;
  p.surface = surface;
  p.albedo = albedo;
  p.label = label;
  p.center = {x, y, 0.5 * (z0 + z1)};
  p.half = {radius, radius, 0.5 * (z1 - z0)};
  return p;
}

Primitive make_ellipsoid(const Eigen::Vector3d& center, const Eigen::Vector3d& radii, double yaw,
                         uint32_t label, float albedo, Surface surface) {
  Primitive p = make_box(center, radii, yaw, label, albedo, surface);
  p.shape = Shape::kEllipsoid;
  return p;
}

bool intersect(const Primitive& primitive, const Ray& ray, double t_min, double t_max, Hit* hit) {
  switch (primitive.shape) {
    case Shape::kBox:
      return intersect_box(primitive, ray, t_min, t_max, hit);
    case Shape::kCylinder:
      return intersect_cylinder(primitive, ray, t_min, t_max, hit);
    case Shape::kEllipsoid:
      return intersect_ellipsoid(primitive, ray, t_min, t_max, hit);
  }
  return false;
}

Footprint footprint(const Primitive& p) {
  double ex = 0, ey = 0;
  const double c = std::abs(p.cos_yaw), s = std::abs(p.sin_yaw);
  switch (p.shape) {
    case Shape::kBox:
      ex = c * p.half.x() + s * p.half.y();
      ey = s * p.half.x() + c * p.half.y();
      break;
    case Shape::kCylinder:
      ex = ey = p.half.x();
      break;
    case Shape::kEllipsoid:
      // Extent of a rotated ellipse along x and y.
      ex = std::hypot(c * p.half.x(), s * p.half.y());
      ey = std::hypot(s * p.half.x(), c * p.half.y());
      break;
  }
  return {p.center.x() - ex, p.center.y() - ey,         p.center.x() + ex,
          p.center.y() + ey, p.center.z() - p.half.z(), p.center.z() + p.half.z()};
}

bool trace_brute_force(const std::vector<Primitive>& primitives, const Ray& ray, double t_min,
                       double t_max, Hit* hit) {
  bool found = false;
  double best = t_max;
  for (size_t i = 0; i < primitives.size(); ++i) {
    Hit h;
    // Equal entries keep the lower index.
    if (intersect(primitives[i], ray, t_min, best, &h) && (!found || h.t_enter < best)) {
      *hit = h;
      hit->primitive = static_cast<int32_t>(i);
      best = h.t_enter;
      found = true;
    }
  }
  return found;
}

SceneGrid::SceneGrid(std::vector<Primitive> primitives, double cell_size)
    : primitives_(std::move(primitives)), cell_(cell_size) {
  PS_CHECK(cell_size > 0 && std::isfinite(cell_size),
           "SceneGrid: cell size must be positive, got {}", cell_size);
  PS_CHECK(primitives_.size() < static_cast<size_t>(std::numeric_limits<int32_t>::max()),
           "SceneGrid: {} primitives, at most 2^31 - 1 supported", primitives_.size());
  if (primitives_.empty()) return;
  std::vector<Footprint> feet;
  feet.reserve(primitives_.size());
  double x0 = kInf, y0 = kInf, x1 = -kInf, y1 = -kInf;
  for (const Primitive& p : primitives_) {
    const Footprint f = footprint(p);
    PS_CHECK(
        std::isfinite(f.x0) && std::isfinite(f.x1) && std::isfinite(f.y0) && std::isfinite(f.y1),
        "SceneGrid: a primitive has a non-finite position or size");
    feet.push_back(f);
    x0 = std::min(x0, f.x0), y0 = std::min(y0, f.y0), x1 = std::max(x1, f.x1),
    y1 = std::max(y1, f.y1);
  }
  x0_ = x0;
  y0_ = y0;
  const double cells_x = std::floor((x1 - x0) / cell_) + 1,
               cells_y = std::floor((y1 - y0) / cell_) + 1;
  PS_CHECK(cells_x * cells_y < 2e8,
           "SceneGrid: {:.0f} x {:.0f} cells of {} m is too many; use larger cells", cells_x,
           cells_y, cell_);
  nx_ = static_cast<int>(cells_x);
  ny_ = static_cast<int>(cells_y);
  const auto cell_range = [&](const Footprint& f, int* ix0, int* iy0, int* ix1, int* iy1) {
    *ix0 = std::clamp(static_cast<int>(std::floor((f.x0 - x0_) / cell_)), 0, nx_ - 1);
    *iy0 = std::clamp(static_cast<int>(std::floor((f.y0 - y0_) / cell_)), 0, ny_ - 1);
    *ix1 = std::clamp(static_cast<int>(std::floor((f.x1 - x0_) / cell_)), 0, nx_ - 1);
    *iy1 = std::clamp(static_cast<int>(std::floor((f.y1 - y0_) / cell_)), 0, ny_ - 1);
  };
  const size_t cells = static_cast<size_t>(nx_) * static_cast<size_t>(ny_);
  cell_begin_.assign(cells + 1, 0);
  cell_top_.assign(cells, -kInf);
  for (const Footprint& f : feet) {
    int ix0, iy0, ix1, iy1;
    cell_range(f, &ix0, &iy0, &ix1, &iy1);
    for (int iy = iy0; iy <= iy1; ++iy)
      for (int ix = ix0; ix <= ix1; ++ix) {
        const size_t c = static_cast<size_t>(iy) * nx_ + ix;
        ++cell_begin_[c + 1];
        cell_top_[c] = std::max(cell_top_[c], f.z1);
      }
  }
  for (size_t c = 0; c < cells; ++c) cell_begin_[c + 1] += cell_begin_[c];
  cell_items_.resize(static_cast<size_t>(cell_begin_[cells]));
  std::vector<int64_t> fill(cell_begin_.begin(), cell_begin_.end() - 1);
  for (size_t i = 0; i < feet.size(); ++i) {
    int ix0, iy0, ix1, iy1;
    cell_range(feet[i], &ix0, &iy0, &ix1, &iy1);
    for (int iy = iy0; iy <= iy1; ++iy)
      for (int ix = ix0; ix <= ix1; ++ix)
        cell_items_[static_cast<size_t>(fill[static_cast<size_t>(iy) * nx_ + ix]++)] =
            static_cast<int32_t>(i);
  }
}

bool SceneGrid::trace(const Ray& ray, double t_min, double t_max, Hit* hit) const {
  if (primitives_.empty() || !(t_max >= t_min)) return false;
  // Clip [t_min, t_max] to the grid's rectangle.
  double t0 = t_min, t1 = t_max;
  const double lo[2] = {x0_, y0_}, hi[2] = {x0_ + nx_ * cell_, y0_ + ny_ * cell_};
  for (int a = 0; a < 2; ++a) {
    const double o = ray.origin[a], d = ray.dir[a];
    if (std::abs(d) < kTiny) {
      if (o < lo[a] || o > hi[a]) return false;
      continue;
    }
    double ta = (lo[a] - o) / d, tb = (hi[a] - o) / d;
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
  }
  if (t0 > t1) return false;

  const double px = ray.origin.x() + t0 * ray.dir.x(), py = ray.origin.y() + t0 * ray.dir.y();
  int ix = std::clamp(static_cast<int>(std::floor((px - x0_) / cell_)), 0, nx_ - 1);
  int iy = std::clamp(static_cast<int>(std::floor((py - y0_) / cell_)), 0, ny_ - 1);
  const int step_x = ray.dir.x() > 0 ? 1 : -1, step_y = ray.dir.y() > 0 ? 1 : -1;
  const auto first_crossing = [&](double o, double d, int i, int step, double origin) {
    if (std::abs(d) < kTiny) return kInf;
    return (origin + (i + (step > 0 ? 1 : 0)) * cell_ - o) / d;
  };
  double next_x = first_crossing(ray.origin.x(), ray.dir.x(), ix, step_x, x0_);
  double next_y = first_crossing(ray.origin.y(), ray.dir.y(), iy, step_y, y0_);
  const double delta_x = std::abs(ray.dir.x()) < kTiny ? kInf : cell_ / std::abs(ray.dir.x());
  const double delta_y = std::abs(ray.dir.y()) < kTiny ? kInf : cell_ / std::abs(ray.dir.y());

  bool found = false;
  double best = t_max;
  double t_in = t0;
  while (true) {
    const double t_out = std::min({next_x, next_y, t1});
    const size_t c = static_cast<size_t>(iy) * nx_ + ix;
    const double z_low = ray.origin.z() + std::min(t_in * ray.dir.z(), t_out * ray.dir.z());
    if (cell_begin_[c] != cell_begin_[c + 1] && z_low <= cell_top_[c]) {
      for (int64_t k = cell_begin_[c]; k < cell_begin_[c + 1]; ++k) {
        const int32_t i = cell_items_[static_cast<size_t>(k)];
        Hit h;
        if (intersect(primitives_[static_cast<size_t>(i)], ray, t_min, best, &h)) {
          // Equal entries keep the lower index, as the brute force does.
          if (found && (h.t_enter > best || (h.t_enter == best && i > hit->primitive))) continue;
          *hit = h;
          hit->primitive = i;
          best = h.t_enter;
          found = true;
        }
      }
    }
    // A hit inside this cell cannot be beaten by primitives of later cells.
    if ((found && best <= t_out) || t_out >= t1) break;
    if (next_x < next_y) {
      ix += step_x;
      t_in = next_x;
      next_x += delta_x;
    } else {
      iy += step_y;
      t_in = next_y;
      next_y += delta_y;
    }
    if (ix < 0 || ix >= nx_ || iy < 0 || iy >= ny_) break;
  }
  return found;
}

}  // namespace pillarseg::sim
