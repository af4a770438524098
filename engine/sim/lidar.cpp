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
constexpr double kReturnFraction = 0.84;
constexpr double kGrassHeight = 0.07;  // pulses on grass return from within its top layer, m
constexpr double kFoliagePath = 0.45;  // mean free path of a pulse in foliage, m
constexpr double kMinRange = 0.9;      // nearer returns are not reported, m
constexpr double kWeakPower = 0.02;    // below this relative power a return fades out
constexpr float kCurbAlbedo = 0.4f;
// The intensity falls with the range beyond kFalloffStart: divided by 1 + ((range -
// kFalloffStart) / kFalloffScale)^2 (0.79 at 25 m, 0.44 at 40 m). On the real labelled scan the
// median of the non-zero intensities of sidewalk, terrain and vegetation falls from 0.32-0.36
// within 20 m to 0.19-0.25 at 30-40 m and 0.16-0.18 at 40-60 m (road 0.23 -> 0.14 at 30-40 m);
// without the falloff the simulated ones rose with the range (the floor below took the dim ones).
constexpr double kFalloffStart = 12.0, kFalloffScale = 25.0;
// Intensities below a floor read 0: kZeroFloor within kFalloffStart, rising by kZeroFloorSlope a
// metre over the next kZeroFloorRamp m (to 0.12) and level beyond. With the falloff, 17% of the
// simulated sidewalk returns 30-40 m out and 66% 40-60 m out read 0 (the real scan: 15% and 70%;
// terrain 10% and 48%, real 7% and 50%; road 58% at 30-40 m, real 83%; cars 63% at 20-30 m, real
// 81%). The floor before the falloff (rising 0.0085 a metre to 54 m: 0.28 at 40 m) would take
// the dim far returns that the real scan keeps (its far sidewalk and terrain read 0.16-0.25);
// one rising 0.0025 a metre to 54 m kept the far dark cars, which the real scan's read 0
// (docs/simulator.md, experiments 37 and 40).
constexpr double kZeroFloor = 0.04, kZeroFloorSlope = 0.008, kZeroFloorRamp = 10.0;
constexpr double kMinStep = 0.25;     // the ground march's shortest step, m
constexpr int kMaxGroundSteps = 400;  // a pulse grazing the ground this long is lost

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

// The pulse against the ground's height field. It marches along the pulse: from a point
// `gap` above the ground, the ground cannot be reached within gap / (kMaxSlope * horizontal
// - dz) (the smooth relief's slope bound); steps are at least kMinStep long, so that a curb,
// which the bound does not cover, is found when a step ends on its raised side below its top.
// The first step that ends below the ground is bisected to where the pulse meets it: on the
// surface, or on a curb's face where the ground steps up by more than a few centimetres
// within the last interval.
// `below_sensor` is the ground at the pulse's origin (the same for every pulse of a scan).
bool ground_hit(const City& city, const Ray& ray, const GroundSample& below_sensor, double t_max,
                Rng& rng, Return* out) {
  const double dz = ray.dir.z(), horizontal = std::hypot(ray.dir.x(), ray.dir.y());
  const double closing = Relief::kMaxSlope * horizontal - dz;  // fastest the gap can shrink
  const auto ground = [&](double t) {
    return city.ground_at(ray.origin.x() + t * ray.dir.x(), ray.origin.y() + t * ray.dir.y());
  };
  const auto gap_at = [&](double t, const GroundSample& g) {
    return ray.origin.z() + t * dz - g.z;
  };
  double t = 0, gap = gap_at(0.0, below_sensor);
  if (gap <= 0) return false;  // the sensor is below the ground
  double t_prev = 0;
  GroundSample g = below_sensor, g_prev;
  for (int step = 0;; ++step) {
    if (closing <= 0 || t >= t_max || step >= kMaxGroundSteps) return false;
    t_prev = t, g_prev = g;
    t = std::min(t_max, t + std::max(gap / closing, kMinStep));
    g = ground(t);
    gap = gap_at(t, g);
    if (gap <= 0) break;
  }
  double lo = t_prev, hi = t;
  GroundSample g_lo = g_prev;
  while (hi - lo > 2e-3) {
    const double mid = 0.5 * (lo + hi);
    const GroundSample gm = ground(mid);
    if (gap_at(mid, gm) > 0) {
      lo = mid, g_lo = gm;
    } else {
      hi = mid, g = gm;
    }
  }
  if (g.z - g_lo.z > 0.04) {
    // The face of a curb (or of a step between two streets' surfaces).
    *out = {hi, g.label == raw::kTerrain ? raw::kTerrain : raw::kSidewalk,
            g.label == raw::kTerrain ? g.albedo : kCurbAlbedo, horizontal};
    return true;
  }
  double hit = hi;
  // Grass: pulses return from within its top layer, at most kGrassHeight above the ground
  // (which, by the slope bound, changes by at most `closing` per metre of the pulse).
  if (g.label == raw::kTerrain) hit -= rng.uniform() * kGrassHeight / closing;
  *out = {hit, g.label, g.albedo, std::max(-dz, 0.02)};
  return true;
}

// The first surface that answers the pulse: objects (static or moving) before the ground.
bool first_return(const LidarModel& lidar, const City& city, const SceneGrid& moving,
                  const Ray& ray, const GroundSample& below_sensor, Rng& rng, Return* out) {
  Return ground;
  const bool has_ground = ground_hit(city, ray, below_sensor, lidar.max_range, rng, &ground);
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

void LidarModel::vary(uint64_t seed) {
  Rng rng = Rng::derive(seed, 0xBEA3);
  gain = rng.uniform(0.8, 1.2);
  beam_gains.resize(elevation_deg.size());
  beam_dropouts.resize(elevation_deg.size());
  for (size_t b = 0; b < elevation_deg.size(); ++b) {
    beam_gains[b] = rng.uniform(0.85, 1.15);
    beam_dropouts[b] = rng.bernoulli(0.1) ? rng.uniform(0.05, 0.2) : rng.uniform(0.005, 0.03);
    // KITTI's lowest beams return about half as often as the others (their share of the
    // returns below -20 deg is 8.7% in real scans against 13.7% for lossless beams).
    if (elevation_deg[b] < -20.0) beam_dropouts[b] = rng.uniform(0.3, 0.55);
  }
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
  const GroundSample below_sensor = city.ground_at(origin.x(), origin.y());
  std::vector<double> sin_el(static_cast<size_t>(beams)), cos_el(static_cast<size_t>(beams));
  for (int b = 0; b < beams; ++b) {
    const double el = lidar.elevation_deg[static_cast<size_t>(b)] * kPi / 180.0;
    sin_el[static_cast<size_t>(b)] = std::sin(el);
    cos_el[static_cast<size_t>(b)] = std::cos(el);
  }

  // The pulses of azimuth step k (each draws from its own generator: any order gives the same).
  const auto cast_step = [&](int64_t k) {
    const double az = lidar.azimuth(static_cast<int>(k));
    const double ca = std::cos(az), sa = std::sin(az);
    for (int b = 0; b < beams; ++b) {
      Rng rng = Rng::derive(seed, static_cast<uint64_t>(b), static_cast<uint64_t>(k));
      const Eigen::Vector3d dir(cos_el[static_cast<size_t>(b)] * ca,
                                cos_el[static_cast<size_t>(b)] * sa,
                                sin_el[static_cast<size_t>(b)]);
      if (rng.bernoulli(lidar.beam_dropout(b)) || hits_body(lidar, dir)) continue;
      Ray ray{origin, rotation * dir};
      Return ret;
      bool ok = first_return(lidar, city, moving, ray, below_sensor, rng, &ret);
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
      // The intensity: the surface's albedo, a little less at grazing incidence, through this
      // sensor's and this beam's gain, with speckle, falling with the range beyond 12 m; below
      // a floor that rises from 12 to 22 m the HDL-64E reports 0 (most dark cars, much of the
      // far road, half of everything 40-60 m out in KITTI).
      double reflectance = lidar.gain * lidar.beam_gain(b) * ret.albedo *
                               (0.7 + 0.3 * ret.cos_incidence) * (1.0 + 0.15 * rng.normal()) +
                           rng.normal(0.0, 0.02);
      const double beyond = std::max(range - kFalloffStart, 0.0) / kFalloffScale;
      reflectance /= 1.0 + beyond * beyond;
      const double floor =
          kZeroFloor + kZeroFloorSlope * std::clamp(range - kFalloffStart, 0.0, kZeroFloorRamp);
      if (reflectance < floor) reflectance = 0.0;
      reflectance = std::clamp(reflectance, 0.0, 1.0);
      const size_t slot =
          static_cast<size_t>(b) * static_cast<size_t>(steps) + static_cast<size_t>(k);
      points[slot] = {static_cast<float>(range * dir.x()), static_cast<float>(range * dir.y()),
                      static_cast<float>(range * dir.z()), static_cast<float>(reflectance)};
      labels[slot] = ret.label;
      valid[slot] = 1;
    }
  };
  // Runs of kAzimuthRun steps dealt to the threads in turn: the scene's work is uneven around the
  // car, and halves of the circle kept one thread waiting for the other.
  constexpr int64_t kAzimuthRun = 16;
  const int64_t runs = (steps + kAzimuthRun - 1) / kAzimuthRun;
  const int64_t threads = std::min<int64_t>(num_threads(), runs);
  parallel_chunks(threads, [&](int64_t begin, int64_t end, int) {
    for (int64_t first = begin; first < end; ++first)
      for (int64_t run = first; run < runs; run += threads) {
        const int64_t run_end = std::min<int64_t>(steps, (run + 1) * kAzimuthRun);
        for (int64_t k = run * kAzimuthRun; k < run_end; ++k) cast_step(k);
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
