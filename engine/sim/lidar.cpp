#include "engine/sim/lidar.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

#include "core/error.hpp"
#include "core/parallel.hpp"
#include "core/rng.hpp"

namespace pillarseg::sim {

namespace {

constexpr double kPi = std::numbers::pi;
// Share of pulses that return in a simulated street (sky, the ego body and dropouts take the
// rest), measured over simulated sequences; sets the pulses per revolution for a point target.
constexpr double kReturnFraction = 0.89;
constexpr double kGrassHeight = 0.07;  // pulses on grass return from within its top layer, m
constexpr double kFoliagePath = 0.45;  // mean free path of a pulse in foliage, m
constexpr double kMinRange = 0.9;      // nearer returns are not reported, m
constexpr double kWeakPower = 0.02;    // below this relative power a return fades out
constexpr float kCurbAlbedo = 0.32f;

struct Return {
  double t = 0;
  uint32_t label = 0;
  double albedo = 0;
  double cos_incidence = 1;  // |cos| of the angle between the pulse and the surface normal
};

// The ego body blocks the pulse (the sensor is outside the box, above it).
bool hits_body(const LidarModel& lidar, const Eigen::Vector3d& dir) {
  double t_enter = -std::numeric_limits<double>::infinity(),
         t_exit = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) {
    if (std::abs(dir[a]) < 1e-12) {
      if (lidar.body_min[a] > 0 || lidar.body_max[a] < 0) return false;
      continue;
    }
    double ta = lidar.body_min[a] / dir[a], tb = lidar.body_max[a] / dir[a];
    if (ta > tb) std::swap(ta, tb);
    t_enter = std::max(t_enter, ta);
    t_exit = std::min(t_exit, tb);
  }
  return t_enter <= t_exit && t_exit > 0;
}

// The pulse against the ground: road level z = 0, and raised surfaces at curb height. A pulse
// that passes curb height over road-level ground and would reach road level under a raised
// surface hits the curb face between; it is found by stepping along the ray and bisecting.
bool ground_hit(const City& city, const Ray& ray, double t_max, Rng& rng, Return* out) {
  const double dz = ray.dir.z();
  if (dz > -1e-6) return false;
  const double h = city.curb_height(), oz = ray.origin.z();
  const auto ground = [&](double t) {
    return city.ground_at(ray.origin.x() + t * ray.dir.x(), ray.origin.y() + t * ray.dir.y());
  };
  const double t_raised = (h - oz) / dz;
  if (t_raised > t_max) return false;
  GroundSample g = ground(t_raised);
  if (g.raised) {
    double t = t_raised;
    if (g.label == raw::kTerrain) t -= rng.uniform() * (t_raised - (h + kGrassHeight - oz) / dz);
    *out = {t, g.label, g.albedo, -dz};
    return true;
  }
  const double t_road = -oz / dz;
  const double horizontal = std::hypot(ray.dir.x(), ray.dir.y());
  const int steps =
      std::max(1, static_cast<int>(std::ceil((t_road - t_raised) * horizontal / 0.5)));
  double prev = t_raised;
  for (int i = 1; i <= steps; ++i) {
    const double t = t_raised + (t_road - t_raised) * i / steps;
    g = ground(t);
    if (g.raised) {
      double lo = prev, hi = t;
      for (int it = 0; it < 12; ++it) {
        const double mid = 0.5 * (lo + hi);
        (ground(mid).raised ? hi : lo) = mid;
      }
      if (hi > t_max) return false;
      *out = {hi, raw::kSidewalk, kCurbAlbedo, horizontal};
      return true;
    }
    prev = t;
  }
  if (t_road > t_max) return false;
  *out = {t_road, g.label, g.albedo, -dz};
  return true;
}

// The first surface that answers the pulse: objects (static or moving) before the ground.
bool first_return(const LidarModel& lidar, const City& city, const SceneGrid& moving,
                  const Ray& ray, Rng& rng, Return* out) {
  Return ground;
  const bool has_ground = ground_hit(city, ray, lidar.max_range, rng, &ground);
  const double t_limit = has_ground ? ground.t : lidar.max_range;
  double t_min = kMinRange;
  for (int pass = 0; pass < 6; ++pass) {
    Hit hs, hm;
    const bool on_static = city.static_scene().trace(ray, t_min, t_limit, &hs);
    const bool on_moving = moving.trace(ray, t_min, on_static ? hs.t_enter : t_limit, &hm);
    if (!on_static && !on_moving) break;
    const Hit& hit = on_moving ? hm : hs;
    const Primitive& p =
        (on_moving ? moving : city.static_scene()).primitives()[static_cast<size_t>(hit.primitive)];
    const double cos_incidence = std::abs(hit.normal.dot(ray.dir));
    switch (p.surface) {
      case Surface::kSolid:
        *out = {hit.t_enter, p.label, p.albedo, cos_incidence};
        return true;
      case Surface::kFoliage: {
        // Leaves face every way: the return comes from inside the crown after a free path.
        const double path = -kFoliagePath * std::log(1.0 - rng.uniform());
        if (hit.t_enter + path < hit.t_exit) {
          *out = {hit.t_enter + path, p.label, p.albedo, 0.6};
          return true;
        }
        break;
      }
      case Surface::kMesh:
        if (rng.bernoulli(0.5)) {
          *out = {hit.t_enter, p.label, p.albedo, cos_incidence};
          return true;
        }
        break;
      case Surface::kGlass: {
        const double u = rng.uniform();
        if (u < 0.3) return false;  // lost in the glass
        if (u >= 0.55) {
          *out = {hit.t_enter, p.label, p.albedo, cos_incidence};
          return true;
        }
        break;
      }
    }
    t_min = hit.t_exit + 1e-3;  // passed through: look behind the primitive
  }
  if (!has_ground || ground.t < t_min) return false;
  *out = ground;
  return true;
}

}  // namespace

LidarModel LidarModel::hdl64e(int azimuth_steps) {
  PS_CHECK(azimuth_steps >= 360, "LidarModel: azimuth steps must be >= 360, got {}", azimuth_steps);
  LidarModel m;
  m.azimuth_steps = azimuth_steps;
  m.elevation_deg.reserve(64);
  for (int i = 0; i < 32; ++i) m.elevation_deg.push_back(2.0 - i * (2.0 + 8.33) / 31.0);
  for (int i = 0; i < 32; ++i) m.elevation_deg.push_back(-8.83 - i * (24.9 - 8.83) / 31.0);
  return m;
}

int LidarModel::azimuth_steps_for(int64_t points_per_scan) {
  PS_CHECK(points_per_scan >= 10000 && points_per_scan <= 2000000,
           "points per scan must be in [10000, 2000000], got {}", points_per_scan);
  return static_cast<int>(
      std::lround(static_cast<double>(points_per_scan) / (64.0 * kReturnFraction)));
}

double LidarModel::azimuth(int k) const {
  return -kPi + (k + 0.5) * 2.0 * kPi / azimuth_steps;
}

SimScan cast_scan(const LidarModel& lidar, const City& city, const SceneGrid& moving,
                  const Eigen::Matrix4d& lidar_to_world, uint64_t seed) {
  const int beams = lidar.beams(), steps = lidar.azimuth_steps;
  PS_CHECK(beams > 0 && steps > 0, "cast_scan: the LiDAR has {} beams and {} azimuth steps", beams,
           steps);
  const size_t slots = static_cast<size_t>(beams) * static_cast<size_t>(steps);
  std::vector<Point> points(slots);
  std::vector<uint32_t> labels(slots);
  std::vector<uint8_t> valid(slots, 0);
  const Eigen::Matrix3d rotation = lidar_to_world.topLeftCorner<3, 3>();
  const Eigen::Vector3d origin = lidar_to_world.topRightCorner<3, 1>();
  std::vector<double> sin_el(static_cast<size_t>(beams)), cos_el(static_cast<size_t>(beams));
  for (int b = 0; b < beams; ++b) {
    const double el = lidar.elevation_deg[static_cast<size_t>(b)] * kPi / 180.0;
    sin_el[static_cast<size_t>(b)] = std::sin(el);
    cos_el[static_cast<size_t>(b)] = std::cos(el);
  }

  parallel_chunks(steps, [&](int64_t begin, int64_t end, int) {
    for (int64_t k = begin; k < end; ++k) {
      const double az = lidar.azimuth(static_cast<int>(k));
      const double ca = std::cos(az), sa = std::sin(az);
      for (int b = 0; b < beams; ++b) {
        Rng rng = Rng::derive(seed, static_cast<uint64_t>(b), static_cast<uint64_t>(k));
        const Eigen::Vector3d dir(cos_el[static_cast<size_t>(b)] * ca,
                                  cos_el[static_cast<size_t>(b)] * sa,
                                  sin_el[static_cast<size_t>(b)]);
        if (rng.bernoulli(lidar.dropout) || hits_body(lidar, dir)) continue;
        Ray ray{origin, rotation * dir};
        Return ret;
        bool ok = first_return(lidar, city, moving, ray, rng, &ret);
        if (ok) {
          // Weak returns (dark, far, grazing) fade out.
          const double power =
              ret.albedo * (0.3 + 0.7 * ret.cos_incidence) / std::pow(ret.t / 40.0, 2);
          if (power < kWeakPower && rng.uniform() * kWeakPower > power) ok = false;
        }
        if (rng.bernoulli(lidar.outlier_rate)) {
          ret = {rng.uniform(1.5, ok ? ret.t : 30.0), raw::kOutlier, rng.uniform(0.0, 0.2), 1.0};
          ok = true;
        }
        if (!ok) continue;
        const double range = ret.t + rng.normal(0.0, lidar.range_noise);
        const double reflectance = std::clamp(
            ret.albedo * (0.55 + 0.45 * ret.cos_incidence) + rng.normal(0.0, 0.02), 0.0, 1.0);
        const size_t slot =
            static_cast<size_t>(b) * static_cast<size_t>(steps) + static_cast<size_t>(k);
        points[slot] = {static_cast<float>(range * dir.x()), static_cast<float>(range * dir.y()),
                        static_cast<float>(range * dir.z()), static_cast<float>(reflectance)};
        labels[slot] = ret.label;
        valid[slot] = 1;
      }
    }
  });

  SimScan scan;
  const size_t count = static_cast<size_t>(std::count(valid.begin(), valid.end(), uint8_t{1}));
  scan.points.reserve(count);
  scan.labels.reserve(count);
  for (size_t i = 0; i < slots; ++i) {
    if (!valid[i]) continue;
    scan.points.push_back(points[i]);
    scan.labels.push_back(labels[i]);
  }
  return scan;
}

}  // namespace pillarseg::sim
