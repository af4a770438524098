#include "engine/sim/city.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <tuple>
#include <unordered_map>

#include "core/eigen.hpp"
#include "core/error.hpp"

namespace pillarseg::sim {

namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;

constexpr double kPi = std::numbers::pi;
constexpr double kVertexSpacing = 2.0;  // polyline vertices, m
constexpr double kMargin = 170.0;       // main street before and after the ego's drive, m
constexpr double kBackyard = 25.0;      // depth of the backyard band behind the building line, m
constexpr double kSceneCell = 2.0;      // static scene grid cell, m
constexpr double kMaxEgoSpeed = 11.5;   // m/s
constexpr double kCamberWidth = 4.0;    // the camber falls over this much road from the centre, m
// The ground texture's amplitude (albedo x (1 + a t), t uniform in [-1, 1] per 0.6 m cell):
// asphalt and other ground vary widely (the real labelled scan's road cells within 20 m span
// 0.08-0.30 in reflectance, p10-p90), paving and grass much less (sidewalk 0.24-0.36, terrain
// 0.30-0.41: p10-p90 0.3-0.4 of the median, against 0.6 with the asphalt's amplitude).
constexpr double kCoarseTexture = 0.35;
constexpr double kFineTexture = 0.2;

double deg(double d) {
  return d * kPi / 180.0;
}

double wrap(double u, double period) {
  const double r = std::fmod(u, period);
  return r < 0 ? r + period : r;
}

// Hash of an integer lattice point and a salt, uniform in [-1, 1].
double lattice_value(int64_t ix, int64_t iy, uint64_t salt) {
  uint64_t h = static_cast<uint64_t>(ix) * 0x9E3779B97F4A7C15ull;
  h ^= static_cast<uint64_t>(iy) * 0xC2B2AE3D27D4EB4Full;
  h ^= salt * 0x165667B19E3779F9ull;
  h ^= h >> 31;
  h *= 0xBF58476D1CE4E5B9ull;
  h ^= h >> 29;
  return static_cast<double>(h >> 11) * 0x1.0p-52 - 1.0;
}

// Value in [-1, 1] fixed for each 0.6 m cell of the ground: the texture of worn asphalt, pavers
// and grass, so that the reflectance of a surface varies in space and not only per point.
double ground_texture(double x, double y, uint64_t salt) {
  return lattice_value(static_cast<int64_t>(std::floor(x / 0.6)),
                       static_cast<int64_t>(std::floor(y / 0.6)), salt);
}

// Smooth noise in [-1, 1] with features of about `scale` metres: the lattice's values
// interpolated with a smoothstep, so the surface has no steps.
double value_noise(double x, double y, double scale, uint64_t salt) {
  const double fx = x / scale, fy = y / scale;
  const double x0 = std::floor(fx), y0 = std::floor(fy);
  const auto ease = [](double u) { return u * u * (3.0 - 2.0 * u); };
  const double u = ease(fx - x0), v = ease(fy - y0);
  const auto ix = static_cast<int64_t>(x0), iy = static_cast<int64_t>(y0);
  const double a = lattice_value(ix, iy, salt), b = lattice_value(ix + 1, iy, salt);
  const double c = lattice_value(ix, iy + 1, salt), d = lattice_value(ix + 1, iy + 1, salt);
  return (1 - v) * ((1 - u) * a + u * b) + v * ((1 - u) * c + u * d);
}

double sum_waves(const std::vector<Relief::Wave>& waves, double x, double y) {
  double z = 0;
  for (const Relief::Wave& w : waves) z += w.amplitude * std::sin(w.kx * x + w.ky * y + w.phase);
  return z;
}

// The squared distance from q to the segment from a along ab, len2 = |ab|^2: to the foot of the
// perpendicular, u = clamp((q - a).ab / len2, 0, 1) along it, dividing only where u lies inside.
double point_segment_distance2(const Vector2d& q, const Vector2d& a, const Vector2d& ab,
                               double len2) {
  const double along = (q - a).dot(ab);
  const double u = !(len2 > 0) || along < 0 ? 0.0 : along >= len2 ? 1.0 : along / len2;
  return (q - (a + u * ab)).squaredNorm();
}

double point_segment_distance(const Vector2d& q, const Vector2d& a, const Vector2d& b) {
  const Vector2d ab = b - a;
  return std::sqrt(point_segment_distance2(q, a, ab, ab.squaredNorm()));
}

// Discs of ground taken by static things, so that new ones are not put on top of old ones.
class Occupancy {
 public:
  bool free(double x, double y, double r) const {
    const int64_t cx = cell(x), cy = cell(y);
    for (int64_t iy = cy - 1; iy <= cy + 1; ++iy)
      for (int64_t ix = cx - 1; ix <= cx + 1; ++ix) {
        const auto it = cells_.find(key(ix, iy));
        if (it == cells_.end()) continue;
        for (const Vector3d& d : it->second)
          if (std::hypot(d.x() - x, d.y() - y) < d.z() + r) return false;
      }
    return true;
  }
  void add(double x, double y, double r) { cells_[key(cell(x), cell(y))].push_back({x, y, r}); }

 private:
  static constexpr double kCell = 4.0;  // larger than any two radii together
  static int64_t cell(double v) { return static_cast<int64_t>(std::floor(v / kCell)); }
  static int64_t key(int64_t ix, int64_t iy) { return ix * 1000003 + iy; }
  std::unordered_map<int64_t, std::vector<Vector3d>> cells_;
};

}  // namespace

// ---- Street ------------------------------------------------------------------------------

void StreetSide::set_edges(double road_half_width, double backyard) {
  e_road = road_half_width;
  e_bike = e_road + bike;
  e_curb = e_bike + parking;
  e_lawn = e_curb + lawn;
  e_walk = e_lawn + sidewalk;
  e_front = e_walk + front;
  e_back = e_front + backyard;
}

double StreetSide::yard_offset(double a) const {
  const double t = std::max(0.0, a - e_walk);
  const double reach = std::abs(yard_drop);
  const double drop = reach > 0 ? -yard_drop * (1.0 - std::exp(-yard_slope * t / reach)) : 0.0;
  return terrain_offset + drop;
}

Street::Street(std::vector<Vector2d> polyline) : points(std::move(polyline)) {
  PS_CHECK(points.size() >= 2, "Street: a centre line needs at least 2 points, got {}",
           points.size());
  arc.assign(points.size(), 0.0);
  for (size_t i = 1; i < points.size(); ++i)
    arc[i] = arc[i - 1] + (points[i] - points[i - 1]).norm();
  for (size_t i = 0; i + 1 < points.size(); ++i) {
    segment_vector.push_back(points[i + 1] - points[i]);
    segment_length2.push_back(segment_vector.back().squaredNorm());
  }
}

StreetFrame Street::at(double s) const {
  s = std::clamp(s, 0.0, length());
  const int n = segments();
  const int j = std::clamp(
      static_cast<int>(std::upper_bound(arc.begin(), arc.end(), s) - arc.begin()) - 1, 0, n - 1);
  const double len = arc[j + 1] - arc[j];
  const double u = len > 0 ? (s - arc[j]) / len : 0.0;
  const auto seg_tangent = [&](int k) { return (points[k + 1] - points[k]).normalized().eval(); };
  Vector2d t = seg_tangent(j);
  if (u < 0.5 && j > 0) {
    const double w = u + 0.5;
    t = ((1 - w) * seg_tangent(j - 1) + w * t).normalized();
  } else if (u >= 0.5 && j < n - 1) {
    const double w = u - 0.5;
    t = ((1 - w) * t + w * seg_tangent(j + 1)).normalized();
  }
  return {points[j] + u * (points[j + 1] - points[j]), t, Vector2d(-t.y(), t.x())};
}

Vector2d Street::point(double s, double d) const {
  const StreetFrame f = at(s);
  return f.p + d * f.normal;
}

int Street::project(const Vector2d& q, int hint, double* s, double* d) const {
  const int n = segments();
  const auto dist2 = [&](int k) {
    const auto i = static_cast<size_t>(k);
    return point_segment_distance2(q, points[i], segment_vector[i], segment_length2[i]);
  };
  // Walks from the hint while the next segment is nearer, comparing the distances as rounded
  // square roots: sqrt is monotonic, so a smaller square is not farther, and only a smaller
  // square within a few ulps (its root may round to the same value) needs the roots.
  const auto farther_or_equal = [](double d2k, double d2best) {
    if (d2k >= d2best) return true;
    if (d2k < d2best * (1.0 - 1e-14)) return false;
    return std::sqrt(d2k) >= std::sqrt(d2best);
  };
  int j = std::clamp(hint, 0, n - 1);
  double best = dist2(j);
  for (int step : {-1, 1}) {
    while (j + step >= 0 && j + step < n) {
      const double dk = dist2(j + step);
      if (farther_or_equal(dk, best)) break;
      best = dk;
      j += step;
    }
  }
  const Vector2d a = points[j];
  const double len = arc[j + 1] - arc[j];
  const Vector2d t = (points[j + 1] - a) / len;
  double u = (q - a).dot(t);
  if (j > 0) u = std::max(u, 0.0);
  if (j < n - 1) u = std::min(u, len);
  *s = arc[j] + u;
  *d = t.x() * (q.y() - a.y()) - t.y() * (q.x() - a.x());
  return j;
}

Zone Street::zone(double s, double d) const {
  if (s < 0 || s > length()) return Zone::kOutside;
  const StreetSide& side = side_of(d);
  const double a = std::abs(d);
  if (a < side.e_road) return Zone::kRoad;
  if (a < side.e_bike) return Zone::kBikeLane;
  if (a < side.e_curb) return Zone::kParking;
  if (a < side.e_lawn) return Zone::kLawn;
  if (a < side.e_walk) return Zone::kSidewalk;
  if (a < side.e_front) return Zone::kFront;
  if (a < side.e_back) return Zone::kBack;
  return Zone::kOutside;
}

double Relief::grade_at(double x, double y) const {
  return sum_waves(grade, x, y);
}

double Relief::hills_at(double x, double y) const {
  return sum_waves(hills, x, y);
}

double EgoDrive::s(double t) const {
  return s0 + v0 * t + (omega > 0 ? accel_amp / omega * (1.0 - std::cos(omega * t)) : 0.0);
}

double EgoDrive::speed(double t) const {
  return v0 + accel_amp * std::sin(omega * t);
}

// ---- generation --------------------------------------------------------------------------

class CityBuilder {
 public:
  CityBuilder(uint64_t seed, int scans) : seed_(seed), scans_(scans) {}

  City build() {
    plan_relief();
    plan_ego();
    plan_main_street();
    plan_side_streets();
    plan_stretches_and_lots();
    plan_crosswalks();
    city_.build_ground_index();
    place_buildings();
    place_yards();
    place_street_furniture();
    place_people_and_two_wheelers();
    place_parked_vehicles();
    plan_traffic();
    plan_cyclists_and_walkers();
    city_.static_scene_ = SceneGrid(std::move(static_), kSceneCell);
    return std::move(city_);
  }

 private:
  Rng stage(uint64_t id) const { return Rng::derive(seed_, id); }

  uint32_t new_instance() {
    PS_CHECK(next_instance_ < 65536,
             "simulated city has more than 65535 object instances (a .label holds 16 bits)");
    return next_instance_++;
  }

  // True when q lies in no band of another street up to its front yards, and not closer than
  // `own_min` to the centre of its own street k (curves bring far points of a side closer).
  bool clear_of_streets(const Vector2d& q, int k, Zone own_min) const {
    std::array<StreetCoord, 8> near;
    const int n = city_.locate(q.x(), q.y(), &near);
    for (int i = 0; i < n; ++i) {
      const StreetCoord& c = near[static_cast<size_t>(i)];
      if (c.street == k ? c.zone < own_min : c.zone < Zone::kBack) return false;
    }
    return true;
  }

  double heading(const Vector2d& t) const { return std::atan2(t.y(), t.x()); }

  // Placement at arc length s, distance a from the centre line on `side` of street k, heading
  // along the street plus yaw_offset; its z is the ground there.
  Placement on_street(int k, int side, double s, double a, double yaw_offset = 0.0) const {
    const Street& st = city_.streets_[static_cast<size_t>(k)];
    const StreetFrame f = st.at(s);
    const Vector2d q = f.p + (side == 0 ? -a : a) * f.normal;
    return {q.x(), q.y(), city_.ground_z(q.x(), q.y()), heading(f.tangent) + yaw_offset};
  }

  uint32_t ground_label(const Placement& p) const { return city_.ground_at(p.x, p.y).label; }

  // ---- layout ----

  // The ground's relief, curb height and material albedos of this city.
  void plan_relief() {
    Rng rng = stage(13);
    Relief& r = city_.relief_;
    city_.curb_height_ = rng.uniform(0.10, 0.16);
    r.camber = rng.uniform(0.01, 0.025);
    r.walk_slope = rng.uniform(0.005, 0.025);
    r.roughness = rng.uniform(0.02, 0.06);
    // Waves of wavelength L and slope g have amplitude g L / (2 pi).
    const auto wave = [&](double l0, double l1, double g0, double g1) {
      Relief::Wave w;
      const double length = rng.uniform(l0, l1), direction = rng.uniform(-kPi, kPi);
      const double slope = rng.uniform(g0, g1);
      w.kx = 2 * kPi / length * std::cos(direction);
      w.ky = 2 * kPi / length * std::sin(direction);
      w.amplitude = slope * length / (2 * kPi);
      w.phase = rng.uniform(-kPi, kPi);
      return w;
    };
    for (int i = 0; i < 3; ++i) r.grade.push_back(wave(60.0, 200.0, 0.005, 0.04));
    for (int i = 0; i < 3; ++i) r.hills.push_back(wave(30.0, 100.0, 0.02, 0.07));
    city_.texture_salt_ = static_cast<uint32_t>(rng.next_u64());
    // Materials overlap but keep their usual order, as in KITTI (road 0.20, sidewalk 0.31,
    // terrain 0.34-0.36 at the median): asphalt darker than paving, by a factor drawn per
    // city, and grass a little brighter than the city's paving (the real labelled scan's 0.4 m
    // cells within 20 m: terrain 1.16 times the sidewalk at the median; drawn independently of
    // the paving, grass came out darker than it in 7 of 12 cities and the model learnt to tell
    // the two apart by the street's layout alone).
    city_.road_albedo_ = static_cast<float>(rng.uniform(0.2, 0.34));
    city_.walk_albedo_ = city_.road_albedo_ * static_cast<float>(rng.uniform(1.15, 1.8));
    city_.terrain_albedo_ = city_.walk_albedo_ * static_cast<float>(rng.uniform(1.0, 1.32));
    city_.other_ground_albedo_ = city_.road_albedo_ * static_cast<float>(rng.uniform(0.9, 1.6));
  }

  void plan_ego() {
    Rng rng = stage(1);
    EgoDrive& e = city_.ego_;
    e.v0 = rng.uniform(6.5, 10.0);
    e.accel_amp = rng.uniform(0.0, std::min({1.5, e.v0 - 5.5, kMaxEgoSpeed - e.v0}));
    e.omega = 2 * kPi / rng.uniform(8.0, 20.0);
    e.s0 = kMargin;
    e.sway = rng.uniform(0.0, 0.15);
    e.sway_omega = 2 * kPi / rng.uniform(4.0, 12.0);
    e.pitch_amp = deg(rng.uniform(0.02, 0.08));
    e.roll_amp = deg(rng.uniform(0.02, 0.08));
  }

  void plan_main_street() {
    Rng rng = stage(2);
    const double drive = city_.ego_.s(std::max(0, scans_ - 1) * kScanPeriod) - city_.ego_.s0;
    const double length = 2 * kMargin + drive;
    std::vector<Vector2d> pts{{0.0, 0.0}};
    const double start_heading = rng.uniform(-kPi, kPi);
    double h = start_heading, total = 0.0;
    int last_turn = rng.bernoulli(0.5) ? 1 : -1;
    bool straight = true;
    while (total < length) {
      double piece = 0, curvature = 0;
      if (straight) {
        piece = rng.uniform(40.0, 150.0);
      } else {
        // Curves alternate mostly, and turn back when the street has drifted far from its
        // first heading, so that it never closes on itself.
        const double drift = h - start_heading;
        int turn = rng.bernoulli(0.7) ? -last_turn : last_turn;
        if (std::abs(drift) > deg(30)) turn = drift > 0 ? -1 : 1;
        const double radius = rng.uniform(90.0, 300.0);
        piece = radius * deg(rng.uniform(10.0, 40.0));
        curvature = turn / radius;
        last_turn = turn;
      }
      for (double done = 0; done < piece && total < length;
           done += kVertexSpacing, total += kVertexSpacing) {
        h += 0.5 * curvature * kVertexSpacing;
        pts.push_back(pts.back() + kVertexSpacing * Vector2d(std::cos(h), std::sin(h)));
        h += 0.5 * curvature * kVertexSpacing;
      }
      straight = !straight;
    }
    Street main(std::move(pts));
    main.lanes = rng.bernoulli(0.2) ? 2 : 1;
    main.lane_width = rng.uniform(3.0, 3.5);
    main.road_albedo = city_.road_albedo_ * static_cast<float>(rng.uniform(0.9, 1.1));
    // Bike lanes, where cyclists ride beside the ego's lane; or, one main street in two, a
    // narrow residential street (one lane each way, no bike lanes, no parking) whose curbs
    // are 1-2 m from the ego, as in many KITTI scans.
    const double bike = rng.uniform(1.0, 1.6);
    const bool narrow = rng.bernoulli(0.5);
    if (narrow) main.lanes = 1, main.lane_width = rng.uniform(2.75, 3.25);
    for (StreetSide& side : main.sides) {
      side.bike = narrow ? 0.0 : bike;
      side.parking = rng.bernoulli(0.6) && !narrow ? rng.uniform(2.1, 2.5) : 0.0;
      // The sidewalk at the curb on most sides (in the real labelled scan no grass touches the
      // road), a tree lawn between curb and sidewalk on few.
      side.lawn = rng.bernoulli(0.15) ? rng.uniform(1.2, 3.5) : 0.0;
      side.sidewalk = rng.uniform(2.0, 5.5);
      side.front = rng.bernoulli(0.75) ? rng.uniform(2.0, 8.0) : rng.uniform(0.0, 2.0);
      side.set_edges(main.lanes * main.lane_width, kBackyard);
    }
    city_.ego_.lane_offset = -(main.lanes - 0.5) * main.lane_width;
    city_.streets_.push_back(std::move(main));
    city_.side_angle_.push_back(0.0);
    attach_s_.push_back(0.0);
    attach_side_.push_back(0);
  }

  // Distance from q to the nearest centre-line vertex of the streets so far, leaving out the
  // main street's vertices within 80 m (of arc) of where a new side street leaves it at sx,
  // and the side street leaving at sx on the other side (it goes the opposite way).
  double distance_to_streets(const Vector2d& q, double sx) const {
    double best = std::numeric_limits<double>::infinity();
    for (size_t k = 0; k < city_.streets_.size(); ++k) {
      if (k != 0 && attach_s_[k] == sx) continue;
      const Street& st = city_.streets_[k];
      for (size_t i = 0; i < st.points.size(); ++i)
        if (k != 0 || std::abs(st.arc[i] - sx) > 80.0)
          best = std::min(best, (st.points[i] - q).squaredNorm());
    }
    return std::sqrt(best);
  }

  void plan_side_streets() {
    Rng rng = stage(3);
    const double main_length = city_.streets_[0].length();
    for (double sx = rng.uniform(30.0, 70.0); sx < main_length - 30.0;
         sx += rng.uniform(55.0, 100.0)) {
      const double r = rng.uniform();
      for (int side = 0; side < 2; ++side) {
        const bool wanted = r < 0.4 || (r < 0.7 ? side == 1 : side == 0);
        const double angle = deg(rng.uniform(-12.0, 12.0));
        const double length = rng.uniform(90.0, 170.0);
        const double curvature = rng.uniform(-1.0 / 500.0, 1.0 / 500.0);
        if (!wanted) continue;
        const StreetFrame f = city_.streets_[0].at(sx);
        const Vector2d out = side == 1 ? f.normal : Vector2d(-f.normal);
        double h = std::atan2(out.y(), out.x()) + angle;
        std::vector<Vector2d> pts{f.p};
        for (double done = 0; done < length; done += kVertexSpacing) {
          h += 0.5 * curvature * kVertexSpacing;
          const Vector2d next = pts.back() + kVertexSpacing * Vector2d(std::cos(h), std::sin(h));
          h += 0.5 * curvature * kVertexSpacing;
          // Stop well short of any other street (other side streets, or the main street again).
          if (done > 20.0 && distance_to_streets(next, sx) < 35.0) {
            pts.resize(pts.size() > 8 ? pts.size() - 7 : 1);
            break;
          }
          pts.push_back(next);
        }
        if (static_cast<double>(pts.size() - 1) * kVertexSpacing < 45.0) continue;
        Street st(std::move(pts));
        st.lanes = 1;
        st.lane_width = rng.uniform(2.9, 3.3);
        st.road_albedo = city_.road_albedo_ * static_cast<float>(rng.uniform(0.9, 1.1));
        const double bike = rng.bernoulli(0.25) ? rng.uniform(1.3, 1.6) : 0.0;
        for (StreetSide& ss : st.sides) {
          ss.bike = bike;
          ss.parking = rng.bernoulli(0.5) ? rng.uniform(2.1, 2.4) : 0.0;
          ss.lawn = rng.bernoulli(0.15) ? rng.uniform(1.0, 3.0) : 0.0;
          ss.sidewalk = rng.uniform(1.8, 5.0);
          ss.front = rng.uniform(0.0, 8.0);
          ss.set_edges(st.lane_width, kBackyard);
        }
        city_.streets_.push_back(std::move(st));
        city_.side_angle_.push_back(angle);
        attach_s_.push_back(sx);
        attach_side_.push_back(side);
      }
    }
  }

  void plan_stretches_and_lots() {
    Rng rng = stage(4), levels = stage(14);
    for (Street& st : city_.streets_) {
      const bool is_main = &st == &city_.streets_[0];
      for (StreetSide& side : st.sides) {
        // The yards meet the back of the sidewalk at its level and, on most sides, fall away
        // beyond it and level off a few decimetres below (StreetSide::yard_offset).
        side.terrain_offset = levels.uniform(-0.06, 0.02);
        side.yard_drop =
            levels.bernoulli(0.7) ? levels.uniform(0.2, 0.6) : -levels.uniform(0.0, 0.15);
        side.yard_slope = levels.uniform(0.01, 0.06);
        for (double s = 0; s < st.length();) {
          s += rng.uniform(15.0, 45.0);
          side.stretch_end.push_back(s);
          side.stretch_parking.push_back(side.parking > 0 && rng.bernoulli(0.35) ? 1 : 0);
        }
        for (double s = 0; s < st.length();) {
          Lot lot;
          lot.s0 = s;
          s += rng.uniform(8.0, 28.0);
          lot.s1 = s;
          lot.building = rng.bernoulli(is_main ? 0.72 : 0.65);
          lot.front_label = rng.bernoulli(0.8) ? raw::kTerrain : raw::kOtherGround;
          lot.back_label = rng.bernoulli(0.85) ? raw::kTerrain : raw::kOtherGround;
          // Half of the lots without a building are open greens, most with a building well
          // behind the building line; half of those are crossed by a paved path.
          const bool green = rng.bernoulli(0.5), far = rng.bernoulli(0.7);
          const bool across = rng.bernoulli(0.5), door = rng.bernoulli(1.0 / 3.0);
          const double far_setback = rng.uniform(8.0, 20.0);
          const double path_width = rng.uniform(1.5, 3.5), door_width = rng.uniform(1.2, 2.2);
          const double path_u = rng.uniform(), path_depth = rng.uniform(8.0, 20.0);
          const auto put_path = [&](double width, double depth) {
            const double room = lot.s1 - lot.s0 - width - 2.0;
            if (room <= 0) return;
            lot.path_half = 0.5 * width;
            lot.path_s = lot.s0 + 1.0 + lot.path_half + path_u * room;
            lot.path_depth = depth;
          };
          if (!lot.building && green) {
            lot.open_green = true;
            lot.front_label = lot.back_label = raw::kTerrain;
            if (far) lot.far_setback = far_setback;
            if (across) put_path(path_width, far ? side.front + far_setback : path_depth);
          } else if (lot.building && side.front > 1.5 && door) {
            // A path to the door (into the building's footprint, which covers its end).
            put_path(door_width, side.front + 1.6);
          }
          side.lots.push_back(lot);
        }
      }
    }
  }

  void plan_crosswalks() {
    Rng rng = stage(5);
    Street& main = city_.streets_[0];
    for (size_t k = 1; k < city_.streets_.size(); ++k) {
      Street& st = city_.streets_[k];
      const double cos_angle = std::cos(city_.side_angle_[k]);
      const StreetSide& main_side = main.sides[static_cast<size_t>(attach_side_[k])];
      if (rng.bernoulli(0.8)) {
        const double c0 = main_side.e_curb / cos_angle + 1.0;
        st.crosswalks.emplace_back(c0, c0 + 3.5);
      }
      const double w = std::max(st.sides[0].e_curb, st.sides[1].e_curb) / cos_angle + 1.0;
      for (int dir : {-1, 1})
        if (rng.bernoulli(0.6)) {
          const double near = attach_s_[k] + dir * w, far = attach_s_[k] + dir * (w + 3.5);
          main.crosswalks.emplace_back(std::min(near, far), std::max(near, far));
        }
    }
  }

  // ---- static things ----

  void place_buildings() {
    Rng rng = stage(6);
    for (size_t k = 0; k < city_.streets_.size(); ++k) {
      Street& st = city_.streets_[k];
      const bool is_main = k == 0;
      for (int side = 0; side < 2; ++side) {
        StreetSide& ss = st.sides[static_cast<size_t>(side)];
        for (Lot& lot : ss.lots) {
          const double width = (lot.s1 - lot.s0) - rng.uniform(0.3, 2.5);
          const double depth = rng.uniform(8.0, 16.0);
          const double height = is_main ? rng.uniform(6.0, 22.0) : rng.uniform(5.0, 16.0);
          const double setback = rng.uniform(0.0, 1.5);
          const float albedo = static_cast<float>(rng.uniform(0.15, 0.5));
          if (!lot.building && lot.far_setback <= 0) continue;
          const double s_mid = 0.5 * (lot.s0 + lot.s1);
          // An open green's building stands far_setback behind the building line.
          const double back = lot.building ? setback : lot.far_setback;
          const StreetFrame f = st.at(s_mid);
          const double sign = side == 0 ? -1.0 : 1.0;
          const Vector2d center = f.p + sign * (ss.e_front + back + 0.5 * depth) * f.normal;
          bool clear = width >= 5.0 && s_mid <= st.length();
          for (double u : {-0.5, 0.0, 0.5})
            for (double v : {-0.5, 0.0, 0.5}) {
              const Vector2d q = center + u * width * f.tangent + v * depth * f.normal;
              clear = clear && clear_of_streets(q, static_cast<int>(k), Zone::kFront);
            }
          if (!clear) {
            lot.building = false;
            lot.far_setback = 0;
            continue;
          }
          emit_building(center, f.tangent, width, depth, height, albedo, rng);
        }
      }
      // A building closes the far end of a side street.
      if (!is_main) {
        const StreetFrame f = st.at(st.length());
        const double width =
            2 * std::max(st.sides[0].e_walk, st.sides[1].e_walk) + rng.uniform(4.0, 16.0);
        const double depth = rng.uniform(8.0, 14.0), height = rng.uniform(6.0, 18.0);
        const Vector2d center = f.p + (rng.uniform(2.0, 6.0) + 0.5 * depth) * f.tangent;
        bool clear = true;
        for (double u : {-0.5, 0.0, 0.5})
          for (double v : {-0.5, 0.0, 0.5}) {
            const Vector2d q = center + u * depth * f.tangent + v * width * f.normal;
            clear = clear && clear_of_streets(q, static_cast<int>(k), Zone::kRoad);
          }
        const float albedo = static_cast<float>(rng.uniform(0.15, 0.5));
        if (clear) emit_building(center, f.normal, width, depth, height, albedo, rng);
      }
    }
  }

  // A building of the given footprint (width along `along`, depth across it) and height above
  // the ground at its centre, standing in the ground down to below its lowest corner. Its
  // facades are not plain boxes: the parts along its width step forward or back and differ in
  // height, and ledges or balconies stick out of the long sides.
  void emit_building(const Vector2d& center, const Vector2d& along, double width, double depth,
                     double height, float albedo, Rng& rng) {
    const Vector2d across(-along.y(), along.x());
    double low = std::numeric_limits<double>::infinity();
    for (double u : {-0.5, 0.5})
      for (double v : {-0.5, 0.5}) {
        const Vector2d q = center + u * width * along + v * depth * across;
        low = std::min(low, city_.ground_z(q.x(), q.y()));
      }
    const double z0 = low - 0.3, top = city_.ground_z(center.x(), center.y()) + height;
    const double yaw = heading(along);
    // The body in two to four parts along the street, each with its own setback and height.
    const int parts = 2 + static_cast<int>(rng.uniform_int(3));
    for (int i = 0; i < parts; ++i) {
      const double u0 = -0.5 + static_cast<double>(i) / parts, u1 = u0 + 1.0 / parts;
      const double setback = rng.bernoulli(0.5) ? rng.uniform(-0.6, 0.6) : 0.0;
      const double part_top = top - (rng.bernoulli(0.3) ? rng.uniform(0.0, 0.3) * height : 0.0);
      const Vector2d c = center + 0.5 * (u0 + u1) * width * along + 0.5 * setback * across;
      static_.push_back(make_box({c.x(), c.y(), 0.5 * (z0 + part_top)},
                                 {0.5 * (u1 - u0) * width + 0.01, 0.5 * (depth - std::abs(setback)),
                                  0.5 * (part_top - z0)},
                                 yaw, raw::kBuilding,
                                 albedo * static_cast<float>(rng.uniform(0.8, 1.2))));
    }
    // Ledges or balconies on both long sides: slabs 0.3-1.2 m deep every storey or so.
    const float detail_albedo = static_cast<float>(rng.uniform(0.1, 0.5));
    for (int face : {-1, 1}) {
      if (!rng.bernoulli(0.5)) continue;
      const double out = rng.uniform(0.3, 1.2), storey = rng.uniform(2.8, 3.4);
      const double span = rng.uniform(0.3, 0.9) * width;
      for (double z = low + storey; z < top - 1.0; z += storey) {
        const Vector2d c = center + face * (0.5 * depth + 0.5 * out) * across;
        static_.push_back(make_box({c.x(), c.y(), z}, {0.5 * span, 0.5 * out, 0.08}, yaw,
                                   raw::kBuilding, detail_albedo));
      }
    }
  }

  // A thin wall (fence or hedge) along street k at distance a, from s0 to s1, in pieces of at
  // most 6 m that follow the curve; pieces that would cross another street are left out.
  // Hedges (foliage) are irregular: pieces of at most 1.5 m, each of its own height and
  // thickness, drawn from rng.
  void wall_along(int k, int side, double s0, double s1, double a, double half_thickness,
                  double height, uint32_t label, float albedo, Surface surface, Rng& rng) {
    const Street& st = city_.streets_[static_cast<size_t>(k)];
    s1 = std::min(s1, st.length());
    const bool hedge = surface == Surface::kFoliage;
    const int pieces = static_cast<int>(std::ceil((s1 - s0) / (hedge ? 1.5 : 6.0)));
    const double base_height = height, base_half = half_thickness;
    for (int i = 0; i < pieces; ++i) {
      if (hedge) {
        height = base_height * rng.uniform(0.75, 1.2);
        half_thickness = base_half * rng.uniform(0.7, 1.25);
      }
      const double a0 = s0 + (s1 - s0) * i / pieces, a1 = s0 + (s1 - s0) * (i + 1) / pieces;
      const Placement p = on_street(k, side, 0.5 * (a0 + a1), a);
      const Vector2d q0 = st.point(a0, side == 0 ? -a : a), q1 = st.point(a1, side == 0 ? -a : a);
      if (!clear_of_streets(q0, k, Zone::kFront) || !clear_of_streets(q1, k, Zone::kFront) ||
          !clear_of_streets({p.x, p.y}, k, Zone::kFront))
        continue;
      // Down into the ground by 0.2 m: the ground under a piece is not level.
      static_.push_back(make_box({p.x, p.y, p.z + 0.5 * height - 0.1},
                                 {0.5 * (a1 - a0) + 0.02, half_thickness, 0.5 * height + 0.1},
                                 p.yaw, label, albedo, surface));
    }
  }

  void add_tree(const Placement& at, Rng& rng) {
    emit_tree(sample_tree(rng), at, raw::kTrunk, raw::kVegetation, static_);
    occupancy_.add(at.x, at.y, 0.6);
  }

  void place_yards() {
    Rng rng = stage(7);
    for (size_t k = 0; k < city_.streets_.size(); ++k) {
      const int ki = static_cast<int>(k);
      for (int side = 0; side < 2; ++side) {
        const StreetSide& ss = city_.streets_[k].sides[static_cast<size_t>(side)];
        for (const Lot& lot : ss.lots) {
          const double boundary = rng.uniform();
          const double fence_height = rng.uniform(1.0, 1.8), hedge_height = rng.uniform(0.8, 1.8);
          const double hedge_half = rng.uniform(0.3, 0.5);
          const bool wire = rng.bernoulli(0.5);
          const float fence_albedo = static_cast<float>(rng.uniform(0.2, 0.45));
          const float leaf_albedo = static_cast<float>(rng.uniform(0.32, 0.48));
          const double gate = rng.uniform(0.0, 3.0);
          const double s0 = lot.s0 + 0.3, s1 = lot.s1 - 0.3 - gate;
          if (s1 - s0 < 2.0) continue;
          // Gaps between buildings are closed by fences or hedges; front gardens of
          // buildings often by hedges or fences too (SemanticKITTI: vegetation 27% and
          // fences 7% of the points).
          // Open greens are open to the sidewalk; elsewhere a path leaves a gap in the wall.
          const bool garden = lot.building && ss.front > 1.5;
          const bool open = lot.open_green;
          // The wall's stretches: [s0, s1] less the path's width and 0.2 m on each side of it.
          std::vector<std::pair<double, double>> spans{{s0, s1}};
          if (lot.path_depth > 0) {
            const double p0 = lot.path_s - lot.path_half - 0.2,
                         p1 = lot.path_s + lot.path_half + 0.2;
            spans = {{s0, std::min(s1, p0)}, {std::max(s0, p1), s1}};
          }
          for (const auto& [w0, w1] : spans) {
            if (open || w1 - w0 < 0.5) continue;
            if ((!lot.building && boundary < 0.35) || (garden && boundary >= 0.6)) {
              wall_along(ki, side, w0, w1, ss.e_walk + 0.05, 0.03, fence_height, raw::kFence,
                         fence_albedo, wire ? Surface::kMesh : Surface::kSolid, rng);
            } else if ((!lot.building && boundary < 0.85) || (garden && boundary < 0.6)) {
              wall_along(ki, side, w0, w1, ss.e_walk + hedge_half + 0.05, hedge_half, hedge_height,
                         raw::kVegetation, leaf_albedo, Surface::kFoliage, rng);
            }
          }
          // Trees and bushes in the yards, off the paths and, on an open green, at least 4 m
          // before its far building.
          const double reach =
              lot.far_setback > 0 ? ss.e_front + lot.far_setback - 4.0 : ss.e_front + 12.0;
          const int trees = lot.building ? (ss.front > 3.0 && rng.bernoulli(0.6) ? 1 : 0)
                                         : 1 + static_cast<int>(rng.uniform_int(3));
          for (int i = 0; i < trees; ++i) {
            const double s = rng.uniform(lot.s0 + 1.0, lot.s1 - 1.0);
            const double a = lot.building
                                 ? ss.e_walk + 0.5 * ss.front
                                 : rng.uniform(ss.e_walk + 2.0, std::max(ss.e_walk + 2.5, reach));
            const Placement p = on_street(ki, side, s, a);
            if (lot.path_depth > 0 && a - ss.e_walk < lot.path_depth + 1.0 &&
                std::abs(s - lot.path_s) < lot.path_half + 1.0)
              continue;
            if (clear_of_streets({p.x, p.y}, ki, Zone::kFront) && occupancy_.free(p.x, p.y, 1.5))
              add_tree(p, rng);
          }
          const int bushes = rng.bernoulli(0.7) ? 1 + static_cast<int>(rng.uniform_int(3)) : 0;
          for (int i = 0; i < bushes; ++i) {
            const double s = rng.uniform(lot.s0 + 1.0, lot.s1 - 1.0);
            const double a =
                ss.e_walk + rng.uniform(1.0, std::max(1.2, lot.building ? ss.front - 0.5 : 10.0));
            const Placement p = on_street(ki, side, s, a);
            const double r = rng.uniform(0.6, 1.6), rz = rng.uniform(0.5, 1.2);
            if (!clear_of_streets({p.x, p.y}, ki, Zone::kFront) || !occupancy_.free(p.x, p.y, r) ||
                (lot.path_depth > 0 && a - ss.e_walk < lot.path_depth + r &&
                 std::abs(s - lot.path_s) < lot.path_half + r))
              continue;
            const double width = r * rng.uniform(0.7, 1.0);
            const double yaw = rng.uniform(0.0, kPi);
            static_.push_back(make_ellipsoid({p.x, p.y, p.z + 0.8 * rz}, {r, width, rz}, yaw,
                                             raw::kVegetation, leaf_albedo, Surface::kFoliage));
            occupancy_.add(p.x, p.y, r);
          }
        }
      }
    }
  }

  // True when the ground at p is one of the labels.
  bool on_ground(const Placement& p, std::initializer_list<uint32_t> labels) const {
    const uint32_t g = ground_label(p);
    return std::find(labels.begin(), labels.end(), g) != labels.end();
  }

  void place_street_furniture() {
    Rng rng = stage(8);
    for (size_t k = 0; k < city_.streets_.size(); ++k) {
      const int ki = static_cast<int>(k);
      const Street& st = city_.streets_[k];
      for (int side = 0; side < 2; ++side) {
        const StreetSide& ss = st.sides[static_cast<size_t>(side)];
        const double to_road = side == 0 ? kPi / 2 : -kPi / 2;  // yaw offset facing the road
        // Street lamps at the curb.
        for (double s = rng.uniform(5.0, 20.0); s < st.length(); s += rng.uniform(25.0, 38.0)) {
          const Placement p = on_street(ki, side, s, ss.e_curb + 0.5, to_road);
          const double height = rng.uniform(6.5, 9.0);
          if (!on_ground(p, {raw::kSidewalk, raw::kTerrain}) || !occupancy_.free(p.x, p.y, 0.5))
            continue;
          emit_street_lamp(p, height, raw::kPole, static_);
          occupancy_.add(p.x, p.y, 0.5);
        }
        // Trees on the lawn, or in tree pits at the curb.
        const bool pits = ss.lawn < 1.2 && rng.bernoulli(0.5);
        if (ss.lawn >= 1.2 || pits) {
          for (double s = rng.uniform(2.0, 10.0); s < st.length(); s += rng.uniform(7.0, 14.0)) {
            const double a = pits ? ss.e_curb + 0.8 : ss.e_curb + 0.5 * ss.lawn;
            const Placement p = on_street(ki, side, s, a);
            const bool shrub = !pits && rng.bernoulli(0.35);
            const double r = rng.uniform(0.4, std::min(1.0, 0.5 * ss.lawn)),
                         rz = rng.uniform(0.4, 0.9);
            const float leaf_albedo = static_cast<float>(rng.uniform(0.32, 0.48));
            if (!on_ground(p, {raw::kSidewalk, raw::kTerrain}) || !occupancy_.free(p.x, p.y, 0.8))
              continue;
            if (!shrub) {
              add_tree(p, rng);
              continue;
            }
            // A shrub on the lawn instead of a tree.
            static_.push_back(make_ellipsoid({p.x, p.y, p.z + 0.8 * rz}, {r, r, rz}, 0.0,
                                             raw::kVegetation, leaf_albedo, Surface::kFoliage));
            occupancy_.add(p.x, p.y, r);
          }
        }
        // Traffic signs facing the traffic of this side (which drives towards +s on the right).
        for (double s = rng.uniform(5.0, 30.0); s < st.length(); s += rng.uniform(25.0, 60.0)) {
          const Placement p = on_street(ki, side, s, ss.e_curb + 0.35, side == 0 ? kPi : 0.0);
          const double height = rng.uniform(2.2, 2.8);
          const int plates = rng.bernoulli(0.3) ? 2 : 1;
          if (!on_ground(p, {raw::kSidewalk, raw::kTerrain}) || !occupancy_.free(p.x, p.y, 0.35))
            continue;
          emit_traffic_sign(p, height, plates, raw::kPole, raw::kTrafficSign, static_);
          occupancy_.add(p.x, p.y, 0.35);
        }
        // Bins (other-object) at the curb, utility cabinets (unlabeled) at the back of the
        // sidewalk, now and then a bus shelter (other-structure).
        for (double s = rng.uniform(5.0, 40.0); s < st.length(); s += rng.uniform(25.0, 55.0)) {
          const Placement p = on_street(ki, side, s, ss.e_lawn + 0.45);
          if (!on_ground(p, {raw::kSidewalk}) || !occupancy_.free(p.x, p.y, 0.45)) continue;
          static_.push_back(make_box({p.x, p.y, p.z + 0.5}, {0.3, 0.3, 0.5}, p.yaw,
                                     raw::kOtherObject, static_cast<float>(rng.uniform(0.1, 0.5))));
          occupancy_.add(p.x, p.y, 0.45);
        }
        for (double s = rng.uniform(10.0, 80.0); s < st.length(); s += rng.uniform(60.0, 120.0)) {
          const Placement p = on_street(ki, side, s, ss.e_walk - 0.3);
          if (!on_ground(p, {raw::kSidewalk}) || !occupancy_.free(p.x, p.y, 0.45)) continue;
          static_.push_back(make_box({p.x, p.y, p.z + 0.65}, {0.35, 0.2, 0.65}, p.yaw,
                                     raw::kUnlabeled, static_cast<float>(rng.uniform(0.2, 0.5))));
          occupancy_.add(p.x, p.y, 0.45);
        }
        for (double s = rng.uniform(40.0, 200.0); s < st.length(); s += rng.uniform(150.0, 300.0)) {
          const Placement p = on_street(ki, side, s, ss.e_walk - 0.9);
          if (!on_ground(p, {raw::kSidewalk}) || ss.sidewalk < 2.5 ||
              !occupancy_.free(p.x, p.y, 1.8))
            continue;
          const Placement back = on_street(ki, side, s, ss.e_walk - 0.3);
          static_.push_back(make_box({back.x, back.y, back.z + 1.2}, {1.6, 0.03, 1.1}, back.yaw,
                                     raw::kOtherStructure, 0.2f, Surface::kGlass));
          static_.push_back(make_box({p.x, p.y, p.z + 2.45}, {1.7, 0.8, 0.05}, p.yaw,
                                     raw::kOtherStructure, 0.3f));
          occupancy_.add(p.x, p.y, 1.8);
        }
      }
    }
  }

  void place_parked_vehicles() {
    Rng rng = stage(9);
    for (size_t k = 0; k < city_.streets_.size(); ++k) {
      const int ki = static_cast<int>(k);
      const Street& st = city_.streets_[k];
      for (int side = 0; side < 2; ++side) {
        const StreetSide& ss = st.sides[static_cast<size_t>(side)];
        if (ss.parking <= 0) continue;
        const double a = ss.e_bike + 0.5 * ss.parking;
        const double along = side == 0 ? 0.0 : kPi;  // parked in the direction of traffic
        for (double s = rng.uniform(0.0, 5.0); s < st.length();) {
          const double u = rng.uniform();
          const bool occupied = rng.bernoulli(0.45);
          AgentKind kind = AgentKind::kCar;
          uint32_t semantic = raw::kCar;
          if (u > 0.88) {
            kind = AgentKind::kMotorcycle, semantic = raw::kMotorcycle;
          } else if (u > 0.82) {
            kind = AgentKind::kTrailer, semantic = raw::kOtherVehicle;
          } else if (u > 0.75) {
            kind = AgentKind::kTruck, semantic = raw::kTruck;
          }
          Agent agent = sample_agent(kind, 0, 0, rng);
          const double gap = rng.uniform(0.6, 3.0);
          if (!occupied) {
            s += rng.uniform(2.0, 7.0);
            continue;
          }
          const double sc = s + 0.5 * agent.length;
          const Placement p = on_street(ki, side, sc, a, along);
          bool fits = ground_label(p) == raw::kParking;
          const double c = std::cos(p.yaw), sn = std::sin(p.yaw);
          for (double fx : {-0.5, 0.5})
            for (double fy : {-0.5, 0.5}) {
              const double x = p.x + fx * agent.length * c - fy * agent.width * sn;
              const double y = p.y + fx * agent.length * sn + fy * agent.width * c;
              fits = fits && !city_.ground_at(x, y).raised && occupancy_.free(x, y, 0.2);
            }
          if (fits) {
            agent.label = label_word(semantic, new_instance());
            emit_agent(agent, p, 0.0, static_);
            for (double fx : {-0.35, 0.0, 0.35})
              occupancy_.add(p.x + fx * agent.length * c, p.y + fx * agent.length * sn,
                             0.5 * agent.width);
          }
          s += agent.length + gap;
        }
      }
    }
  }

  void place_people_and_two_wheelers() {
    Rng rng = stage(10);
    for (size_t k = 0; k < city_.streets_.size(); ++k) {
      const int ki = static_cast<int>(k);
      const Street& st = city_.streets_[k];
      for (int side = 0; side < 2; ++side) {
        const StreetSide& ss = st.sides[static_cast<size_t>(side)];
        // Bicycle racks: 3-6 bicycles side by side at an angle to the street, either in a
        // corral in the parking strip or on the sidewalk with the parking in front kept free.
        for (double s = rng.uniform(5.0, 60.0); s < st.length(); s += rng.uniform(60.0, 140.0)) {
          const int count = 3 + static_cast<int>(rng.uniform_int(4));
          // Racks stand on the sidewalk only where it is wide enough to walk past them.
          const bool corral = ss.parking > 0 && (rng.bernoulli(0.6) || ss.sidewalk < 3.0);
          const double a = corral ? ss.e_bike + 0.5 * ss.parking : ss.e_lawn + 0.6;
          const double sign = rng.bernoulli(0.5) ? 1.0 : -1.0;
          const double angle = sign * rng.uniform(0.5, 0.9);
          std::vector<Placement> rack;
          for (int i = 0; i < count; ++i) {
            const Placement p = on_street(ki, side, s + 0.8 * i, a, angle + rng.uniform(-0.1, 0.1));
            const bool ground_ok = corral ? ground_label(p) == raw::kParking
                                          : on_ground(p, {raw::kSidewalk, raw::kTerrain});
            if (ground_ok && occupancy_.free(p.x, p.y, 0.3)) rack.push_back(p);
          }
          for (const Placement& p : rack) {
            Agent bike = sample_agent(AgentKind::kBicycle, 0, 0, rng);
            bike.label = label_word(raw::kBicycle, new_instance());
            emit_agent(bike, p, 0.0, static_);
            occupancy_.add(p.x, p.y, 0.5);
          }
          if (!rack.empty() && ss.parking > 0)
            for (double f = s - 2.0; f < s + 0.8 * count + 2.0; f += 1.5) {
              const Placement q = on_street(ki, side, f, ss.e_bike + 0.5 * ss.parking);
              occupancy_.add(q.x, q.y, 1.2);
            }
        }
        // Bicycles leaning at the back of the sidewalk, along the street.
        for (const Lot& lot : ss.lots) {
          if (!rng.bernoulli(0.12)) continue;
          const double s = rng.uniform(lot.s0, lot.s1);
          const Placement p = on_street(ki, side, s, ss.e_walk - 0.35, rng.uniform(-0.1, 0.1));
          if (!on_ground(p, {raw::kSidewalk}) || !occupancy_.free(p.x, p.y, 0.4)) continue;
          Agent bike = sample_agent(AgentKind::kBicycle, 0, 0, rng);
          bike.label = label_word(raw::kBicycle, new_instance());
          emit_agent(bike, p, 0.0, static_);
          occupancy_.add(p.x, p.y, 0.6);
        }
        // Standing people: alone or in groups of two or three, on the sidewalk.
        for (double s = rng.uniform(2.0, 35.0); s < st.length(); s += rng.uniform(30.0, 70.0)) {
          const int group = rng.bernoulli(0.6) ? 1 : (rng.bernoulli(0.75) ? 2 : 3);
          const double a = ss.e_lawn + rng.uniform(0.4, std::max(0.5, ss.sidewalk - 0.4));
          const double face = rng.uniform(-kPi, kPi);
          for (int i = 0; i < group; ++i) {
            const Placement p =
                on_street(ki, side, s + 0.7 * i, a + rng.uniform(-0.2, 0.2), face + i * 2.2);
            Agent person = sample_agent(AgentKind::kPerson, 0, 0, rng);
            if (!on_ground(p, {raw::kSidewalk, raw::kTerrain, raw::kOtherGround}) ||
                !occupancy_.free(p.x, p.y, 0.3))
              continue;
            person.label = label_word(raw::kPerson, new_instance());
            emit_agent(person, p, 0.0, static_);
            occupancy_.add(p.x, p.y, 0.3);
          }
        }
        // Bicyclists waiting with their bicycle at the curb (the person is bicyclist 31, the
        // bicycle 11), now and then: a rider on the sidewalk is rare in KITTI, and models
        // trained on many of them put riders on real sidewalks and grass. Motorcyclists stopped
        // in the parking strip (32 on motorcycle 15).
        for (double s = rng.uniform(10.0, 200.0); s < st.length(); s += rng.uniform(150.0, 350.0)) {
          const Placement p = on_street(ki, side, s, ss.e_lawn + 0.5, side == 0 ? 0.0 : kPi);
          Agent rider = sample_agent(AgentKind::kBicyclist, 0, 0, rng);
          if (!on_ground(p, {raw::kSidewalk}) || !occupancy_.free(p.x, p.y, 1.0)) continue;
          rider.label = label_word(raw::kBicyclist, new_instance());
          rider.vehicle_label = label_word(raw::kBicycle, new_instance());
          emit_agent(rider, p, 0.0, static_);
          occupancy_.add(p.x, p.y, 1.0);
        }
        if (ss.parking > 0) {
          for (double s = rng.uniform(20.0, 200.0); s < st.length();
               s += rng.uniform(150.0, 300.0)) {
            const Placement p =
                on_street(ki, side, s, ss.e_bike + 0.5 * ss.parking, side == 0 ? 0.0 : kPi);
            Agent rider = sample_agent(AgentKind::kMotorcyclist, 0, 0, rng);
            if (ground_label(p) != raw::kParking || !occupancy_.free(p.x, p.y, 1.2)) continue;
            rider.label = label_word(raw::kMotorcyclist, new_instance());
            rider.vehicle_label = label_word(raw::kMotorcycle, new_instance());
            emit_agent(rider, p, 0.0, static_);
            occupancy_.add(p.x, p.y, 1.2);
          }
        }
      }
    }
    place_waiting_at_corners(rng);
  }

  // At the corners of each junction, where no car parks, bicyclists wait with their bicycle
  // (at one corner in four) and people wait to cross, at the main street's curb on both sides of
  // the side street.
  void place_waiting_at_corners(Rng& rng) {
    const Street& main = city_.streets_[0];
    for (size_t k = 1; k < city_.streets_.size(); ++k) {
      const int side = attach_side_[k];
      const StreetSide& ms = main.sides[static_cast<size_t>(side)];
      const StreetSide& near_side = city_.streets_[k].sides[side == 0 ? 1 : 0];
      const double half_width = std::max(near_side.e_walk, city_.streets_[k].sides[side].e_walk);
      for (int dir : {-1, 1}) {
        const double s = attach_s_[k] + dir * (half_width / std::cos(city_.side_angle_[k]) +
                                               rng.uniform(0.5, 3.0));
        const double a = ms.e_curb + 0.7;
        const bool cyclist = rng.bernoulli(0.25);
        const Placement p =
            on_street(0, side, s, a, (side == 0 ? 0.0 : kPi) + rng.uniform(-0.3, 0.3));
        if (!on_ground(p, {raw::kSidewalk, raw::kTerrain}) || !occupancy_.free(p.x, p.y, 1.0))
          continue;
        if (cyclist) {
          Agent rider = sample_agent(AgentKind::kBicyclist, 0, 0, rng);
          rider.label = label_word(raw::kBicyclist, new_instance());
          rider.vehicle_label = label_word(raw::kBicycle, new_instance());
          emit_agent(rider, p, 0.0, static_);
        } else {
          for (int i = 0; i < 2; ++i) {
            const Placement q =
                on_street(0, side, s + 0.8 * i, a + rng.uniform(0.0, 0.5), p.yaw + kPi / 2);
            Agent person = sample_agent(AgentKind::kPerson, 0, 0, rng);
            person.label = label_word(raw::kPerson, new_instance());
            emit_agent(person, q, 0.0, static_);
          }
        }
        occupancy_.add(p.x, p.y, 1.0);
      }
    }
  }

  // ---- moving agents ----

  // Fills a route with agents spaced gap_lo..gap_hi apart (plus their lengths), leaving at
  // least gap_lo between the last one and the first one, which follows it on a loop.
  template <class MakeAgent>
  void fill_route(const Route& route, double route_length, double speed, double gap_lo,
                  double gap_hi, Rng& rng, MakeAgent&& make_agent) {
    const double first = rng.uniform(0.0, gap_hi);
    for (double u = first;;) {
      MovingAgent m;
      m.agent = make_agent(rng);
      if (u + m.agent.length + gap_lo > first + route_length) break;
      m.route = route;
      m.u0 = u + 0.5 * m.agent.length;
      m.speed = speed;
      city_.movers_.push_back(m);
      u += m.agent.length + rng.uniform(gap_lo, gap_hi);
    }
  }

  Agent traffic_agent(Rng& rng, double bus_share, double truck_share, double motorcycle_share) {
    const double u = rng.uniform();
    if (u < motorcycle_share) {
      const uint32_t id = new_instance();
      return sample_agent(AgentKind::kMotorcyclist, label_word(raw::kMovingMotorcyclist, id),
                          label_word(raw::kMovingMotorcyclist, id), rng);
    }
    if (u < motorcycle_share + truck_share)
      return sample_agent(AgentKind::kTruck, label_word(raw::kMovingTruck, new_instance()), 0, rng);
    if (u < motorcycle_share + truck_share + bus_share)
      return sample_agent(AgentKind::kBus, label_word(raw::kMovingOtherVehicle, new_instance()), 0,
                          rng);
    return sample_agent(AgentKind::kCar, label_word(raw::kMovingCar, new_instance()), 0, rng);
  }

  Agent moving_bicyclist(Rng& rng) {
    // A moving bicyclist is one object: rider and bicycle are both 253, one instance.
    const uint32_t word = label_word(raw::kMovingBicyclist, new_instance());
    return sample_agent(AgentKind::kBicyclist, word, word, rng);
  }

  // Start of a side street's routes: past the main street's sidewalk.
  double side_route_start(size_t k, double beyond) const {
    const StreetSide& main_side = city_.streets_[0].sides[static_cast<size_t>(attach_side_[k])];
    return (main_side.e_walk + beyond) / std::cos(city_.side_angle_[k]);
  }

  void plan_traffic() {
    Rng rng = stage(11);
    const Street& main = city_.streets_[0];
    const double length = main.length(), lw = main.lane_width;
    const auto vehicle = [&](Rng& r) { return traffic_agent(r, 0.06, 0.08, 0.07); };
    // Oncoming lanes (left of the centre line) and, on four-lane streets, the ego's inner
    // neighbour lane: loops over the whole street, wrapping far from the ego.
    for (int lane = 0; lane < main.lanes; ++lane) {
      Route oncoming{Route::Kind::kLoopBackward, 0, 0.0, length, (lane + 0.5) * lw, 0.0};
      fill_route(oncoming, length, rng.uniform(8.0, 13.0), 10.0, 55.0, rng, vehicle);
    }
    if (main.lanes == 2) {
      Route inner{Route::Kind::kLoopForward, 0, 0.0, length, -0.5 * lw, 0.0};
      fill_route(inner, length, rng.uniform(9.0, 14.0), 12.0, 60.0, rng, vehicle);
    }
    // The car ahead of the ego and the one behind it in its lane drive at its speed.
    for (auto [share, lo, hi] : {std::tuple{0.6, 14.0, 35.0}, std::tuple{0.5, -25.0, -10.0}}) {
      if (!rng.bernoulli(share)) continue;
      MovingAgent m;
      m.agent = sample_agent(AgentKind::kCar, label_word(raw::kMovingCar, new_instance()), 0, rng);
      m.route = Route{Route::Kind::kFollowEgo, 0, 0.0, length, city_.ego_.lane_offset, 0.0};
      m.u0 = rng.uniform(lo, hi);
      city_.movers_.push_back(m);
    }
    // Side streets: vehicles drive out and back (turning at the far end and before the main
    // street, so that they never cross the ego's path).
    for (size_t k = 1; k < city_.streets_.size(); ++k) {
      const Street& st = city_.streets_[k];
      const double s0 = side_route_start(k, 2.0), s1 = st.length() - 5.0;
      if (s1 - s0 < 20.0) continue;
      Route route{Route::Kind::kShuttle, static_cast<int>(k), s0, s1,
                  -0.5 * st.lane_width,  0.5 * st.lane_width};
      fill_route(route, 2 * (s1 - s0), rng.uniform(5.0, 9.0), 15.0, 70.0, rng,
                 [&](Rng& r) { return traffic_agent(r, 0.0, 0.05, 0.1); });
    }
  }

  void plan_cyclists_and_walkers() {
    Rng rng = stage(12);
    for (size_t k = 0; k < city_.streets_.size(); ++k) {
      const Street& st = city_.streets_[k];
      const int ki = static_cast<int>(k);
      const double start = k == 0 ? 0.0 : side_route_start(k, 0.5);
      const double end = st.length() - 1.0;
      if (end - start < 20.0) continue;
      // Bicyclists in the bike lanes, out on the right and back on the left.
      if (st.sides[0].bike > 0) {
        const double a = st.sides[0].e_road + 0.5 * st.sides[0].bike;
        const double b = st.sides[1].e_road + 0.5 * st.sides[1].bike;
        Route route{Route::Kind::kShuttle, ki, start, end, -a, b};
        fill_route(route, 2 * (end - start), rng.uniform(3.5, 6.5), 20.0, 65.0, rng,
                   [&](Rng& r) { return moving_bicyclist(r); });
      }
      // Walkers on each sidewalk, on two tracks (out and back) so they do not meet.
      for (int side = 0; side < 2; ++side) {
        const StreetSide& ss = st.sides[static_cast<size_t>(side)];
        const double sign = side == 0 ? -1.0 : 1.0;
        // Between the racks and waiting cyclists at the curb side of the sidewalk and the
        // cabinets and leaning bicycles at its back.
        const double out = ss.e_lawn + rng.uniform(0.42, 0.55) * ss.sidewalk;
        const double back = ss.e_lawn + rng.uniform(0.62, 0.72) * ss.sidewalk;
        Route route{Route::Kind::kShuttle, ki, start, end, sign * out, sign * back};
        fill_route(route, 2 * (end - start), rng.uniform(1.0, 1.6), 35.0, 100.0, rng, [&](Rng& r) {
          return sample_agent(AgentKind::kPerson, label_word(raw::kMovingPerson, new_instance()), 0,
                              r);
        });
      }
    }
  }

  uint64_t seed_;
  int scans_;
  City city_;
  std::vector<Primitive> static_;
  Occupancy occupancy_;
  uint32_t next_instance_ = 1;
  std::vector<double> attach_s_;  // per street: arc length on the main street where it leaves it
  std::vector<int> attach_side_;  // per street: the main street's side it leaves from
};

// ---- City --------------------------------------------------------------------------------

City City::generate(uint64_t seed, int scans) {
  PS_CHECK(scans >= 1, "City::generate: scans must be >= 1, got {}", scans);
  return CityBuilder(seed, scans).build();
}

void City::build_ground_index() {
  double x0 = std::numeric_limits<double>::infinity(), y0 = x0, x1 = -x0, y1 = -x0;
  double reach = 0;
  for (const Street& st : streets_) {
    for (const StreetSide& side : st.sides) reach = std::max(reach, side.e_back);
    for (const Vector2d& p : st.points) {
      x0 = std::min(x0, p.x()), y0 = std::min(y0, p.y());
      x1 = std::max(x1, p.x()), y1 = std::max(y1, p.y());
    }
  }
  const double pad = reach + 2 * index_cell_;
  index_x0_ = x0 - pad;
  index_y0_ = y0 - pad;
  index_nx_ = static_cast<int>(std::ceil((x1 - x0 + 2 * pad) / index_cell_));
  index_ny_ = static_cast<int>(std::ceil((y1 - y0 + 2 * pad) / index_cell_));
  const size_t cells = static_cast<size_t>(index_nx_) * static_cast<size_t>(index_ny_);

  // Per street: the nearest segment to each cell centre within its reach (plus most of a cell
  // diagonal), found by visiting the cells around each segment.
  std::vector<std::vector<std::pair<size_t, IndexEntry>>> per_street(streets_.size());
  std::vector<double> best(cells, 0.0);
  std::vector<int32_t> best_segment(cells, -1);
  const auto cell_of = [&](double v, double origin, int n) {
    return std::clamp(static_cast<int>(std::floor((v - origin) / index_cell_)), 0, n - 1);
  };
  for (size_t k = 0; k < streets_.size(); ++k) {
    const Street& st = streets_[k];
    const double radius = std::max(st.sides[0].e_back, st.sides[1].e_back) + 0.75 * index_cell_;
    std::vector<size_t> touched;
    for (int j = 0; j < st.segments(); ++j) {
      const Vector2d a = st.points[static_cast<size_t>(j)],
                     b = st.points[static_cast<size_t>(j) + 1];
      const int ix0 = cell_of(std::min(a.x(), b.x()) - radius, index_x0_, index_nx_);
      const int ix1 = cell_of(std::max(a.x(), b.x()) + radius, index_x0_, index_nx_);
      const int iy0 = cell_of(std::min(a.y(), b.y()) - radius, index_y0_, index_ny_);
      const int iy1 = cell_of(std::max(a.y(), b.y()) + radius, index_y0_, index_ny_);
      for (int iy = iy0; iy <= iy1; ++iy)
        for (int ix = ix0; ix <= ix1; ++ix) {
          const Vector2d c(index_x0_ + (ix + 0.5) * index_cell_,
                           index_y0_ + (iy + 0.5) * index_cell_);
          const double dist = point_segment_distance(c, a, b);
          if (dist > radius) continue;
          const size_t cell = static_cast<size_t>(iy) * index_nx_ + ix;
          if (best_segment[cell] < 0) {
            touched.push_back(cell);
          } else if (dist >= best[cell]) {
            continue;
          }
          best[cell] = dist;
          best_segment[cell] = j;
        }
    }
    std::sort(touched.begin(), touched.end());
    for (size_t cell : touched) {
      per_street[k].push_back({cell, {static_cast<int32_t>(k), best_segment[cell]}});
      best_segment[cell] = -1;
    }
  }
  index_begin_.assign(cells + 1, 0);
  for (const auto& list : per_street)
    for (const auto& [cell, entry] : list) ++index_begin_[cell + 1];
  for (size_t c = 0; c < cells; ++c) index_begin_[c + 1] += index_begin_[c];
  index_entries_.resize(static_cast<size_t>(index_begin_[cells]));
  std::vector<int64_t> fill(index_begin_.begin(), index_begin_.end() - 1);
  for (const auto& list : per_street)  // streets in order, so each cell lists them ascending
    for (const auto& [cell, entry] : list)
      index_entries_[static_cast<size_t>(fill[cell]++)] = entry;
}

int City::locate(double x, double y, std::array<StreetCoord, 8>* out) const {
  const double fx = std::floor((x - index_x0_) / index_cell_),
               fy = std::floor((y - index_y0_) / index_cell_);
  if (!(fx >= 0 && fy >= 0 && fx < index_nx_ && fy < index_ny_)) return 0;
  const size_t c = static_cast<size_t>(fy) * index_nx_ + static_cast<size_t>(fx);
  int n = 0;
  for (int64_t k = index_begin_[c]; k < index_begin_[c + 1] && n < 8; ++k) {
    const IndexEntry& e = index_entries_[static_cast<size_t>(k)];
    const Street& st = streets_[static_cast<size_t>(e.street)];
    StreetCoord& sc = (*out)[static_cast<size_t>(n++)];
    sc.street = e.street;
    st.project({x, y}, e.segment, &sc.s, &sc.d);
    sc.zone = st.zone(sc.s, sc.d);
  }
  return n;
}

GroundSample City::ground_at(double x, double y) const {
  std::array<StreetCoord, 8> near;
  const int n = locate(x, y, &near);
  int owner = -1, roadlike = 0;
  // Hills fade in beyond the sidewalks of every street near: the least of the streets' weights,
  // continuous wherever the owner changes.
  double hill_weight = 1.0;
  for (int i = 0; i < n; ++i) {
    const StreetCoord& c = near[static_cast<size_t>(i)];
    if (c.zone <= Zone::kParking) ++roadlike;
    if (owner < 0 || c.zone < near[static_cast<size_t>(owner)].zone) owner = i;
    if (c.zone != Zone::kOutside) {
      const StreetSide& side = streets_[static_cast<size_t>(c.street)].side_of(c.d);
      hill_weight = std::min(
          hill_weight, std::clamp((std::abs(c.d) - side.e_walk) / Relief::kHillFade, 0.0, 1.0));
    }
  }
  GroundSample g;
  const uint64_t salt = texture_salt_;
  const double texture = ground_texture(x, y, salt);
  // A few cells of every surface are much darker (patches, wet or dirty spots): real scans
  // hold returns of reflectance near 0 on every kind of ground.
  const double patch = lattice_value(static_cast<int64_t>(std::floor(x / 1.7)),
                                     static_cast<int64_t>(std::floor(y / 1.7)), salt + 7) > 0.84
                           ? 0.3
                           : 1.0;
  const double bumps = value_noise(x, y, 1.3, salt + 1) + 0.5 * value_noise(x, y, 0.45, salt + 2);
  // Within a street's sidewalks the hills weigh 0: their three sines are not evaluated (the sum
  // then differs from grade + 0 x hills at most in the sign of a zero).
  const double hills = hill_weight > 0 ? hill_weight * relief_.hills_at(x, y) : 0.0;
  const double base = relief_.grade_at(x, y) + hills;
  // Height of the raised side at the curb of the owner's street side, and of the terrain
  // between streets (a typical street's).
  const double road_edge = -relief_.camber * kCamberWidth;
  const double curb_top = road_edge + curb_height_;
  if (owner < 0 || near[static_cast<size_t>(owner)].zone == Zone::kOutside) {
    g.label = raw::kTerrain;
    g.albedo = static_cast<float>(terrain_albedo_ * (1.0 + kFineTexture * texture) * patch);
    g.z = base + curb_top + relief_.roughness * bumps;
    return g;
  }
  const StreetCoord& c = near[static_cast<size_t>(owner)];
  const Street& st = streets_[static_cast<size_t>(c.street)];
  const StreetSide& side = st.side_of(c.d);
  const double a = std::abs(c.d);
  g.raised = c.zone > Zone::kParking;
  double albedo = 0.3;
  // Profile across the street: the camber down to the curb, the curb, then sidewalk and lawn
  // rising away from it, flat from the back of the sidewalk on.
  double profile = -relief_.camber * std::min(a, kCamberWidth);
  if (g.raised) profile = curb_top + relief_.walk_slope * (std::min(a, side.e_walk) - side.e_curb);
  double rough = 0.25 * relief_.roughness;  // paved: small waves
  switch (c.zone) {
    case Zone::kRoad:
    case Zone::kBikeLane:
    case Zone::kParking: {
      g.label = raw::kRoad;
      albedo = st.road_albedo;
      if (roadlike >= 2) break;  // inside an intersection: plain asphalt
      bool marked = false;
      for (const auto& [c0, c1] : st.crosswalks)
        marked = marked || (c.s >= c0 && c.s < c1 && wrap(c.d, 1.0) < 0.5);
      if (c.zone == Zone::kParking) {
        const size_t i = static_cast<size_t>(
            std::lower_bound(side.stretch_end.begin(), side.stretch_end.end(), c.s) -
            side.stretch_end.begin());
        if (!marked && i < side.stretch_parking.size() && side.stretch_parking[i]) {
          g.label = raw::kParking;
          albedo = other_ground_albedo_;
        }
      } else if (st.lanes == 1) {
        marked = marked || (a < 0.075 && wrap(c.s, 10.0) < 4.0);
      } else {
        marked =
            marked || a < 0.08 || (std::abs(a - st.lane_width) < 0.07 && wrap(c.s, 12.0) < 4.0);
      }
      // Edge line between the lanes and the bike lane or curb.
      marked = marked || (c.zone == Zone::kRoad && a > side.e_road - 0.15);
      if (marked) {
        g.label = raw::kLaneMarking;
        albedo = std::min(0.9, st.road_albedo * (2.4 + 0.6 * lattice_value(c.street, 0, salt + 3)));
      }
      break;
    }
    case Zone::kLawn:
      g.label = raw::kTerrain;
      albedo = terrain_albedo_;
      rough = relief_.roughness;
      profile += std::max(side.terrain_offset, 0.02 - curb_height_);
      break;
    case Zone::kSidewalk:
      g.label = raw::kSidewalk;
      albedo = walk_albedo_;
      break;
    case Zone::kFront:
    case Zone::kBack: {
      const auto it = std::upper_bound(side.lots.begin(), side.lots.end(), c.s,
                                       [](double s, const Lot& lot) { return s < lot.s1; });
      const Lot& lot = it == side.lots.end() ? side.lots.back() : *it;
      g.label = c.zone == Zone::kFront ? lot.front_label : lot.back_label;
      if (lot.on_path(c.s, a - side.e_walk)) g.label = raw::kSidewalk;
      const bool terrain = g.label == raw::kTerrain;
      albedo = terrain                     ? terrain_albedo_
               : g.label == raw::kSidewalk ? walk_albedo_
                                           : other_ground_albedo_;
      rough = terrain ? relief_.roughness
                      : (g.label == raw::kSidewalk ? 0.25 : 0.4) * relief_.roughness;
      // Yards, paved or not, and their paths: the side's yard offset from the back of the
      // sidewalk, returning with the sidewalk's rise to the level of the ground between the
      // streets over the backyards' last kYardLevel m (smoothstep).
      const double u = std::clamp((side.e_back - a) / StreetSide::kYardLevel, 0.0, 1.0);
      profile =
          curb_top + u * u * (3.0 - 2.0 * u) *
                         (relief_.walk_slope * (side.e_walk - side.e_curb) + side.yard_offset(a));
      break;
    }
    case Zone::kOutside:
      break;
  }
  const bool fine = g.label == raw::kSidewalk || g.label == raw::kTerrain;
  g.albedo = static_cast<float>(std::clamp(
      albedo * (1.0 + (fine ? kFineTexture : kCoarseTexture) * texture) * patch, 0.0, 1.0));
  g.z = base + profile + rough * bumps;
  return g;
}

Placement City::mover_pose(const MovingAgent& m, double t, double* travelled) const {
  const Street& st = streets_[static_cast<size_t>(m.route.street)];
  const double u = m.u0 + m.speed * t;
  const double len = m.route.s1 - m.route.s0;
  double s = 0, d = m.route.offset_out;
  bool backward = false;
  switch (m.route.kind) {
    case Route::Kind::kLoopForward:
      s = m.route.s0 + wrap(u, len);
      break;
    case Route::Kind::kLoopBackward:
      s = m.route.s1 - wrap(u, len);
      backward = true;
      break;
    case Route::Kind::kShuttle: {
      const double v = wrap(u, 2 * len);
      backward = v >= len;
      s = backward ? m.route.s1 - (v - len) : m.route.s0 + v;
      d = backward ? m.route.offset_back : m.route.offset_out;
      break;
    }
    case Route::Kind::kFollowEgo:
      s = ego_.s(t) + m.u0;
      break;
  }
  if (travelled) *travelled = m.route.kind == Route::Kind::kFollowEgo ? ego_.s(t) - ego_.s0 : u;
  const StreetFrame f = st.at(s);
  const Vector2d q = f.p + d * f.normal;
  const double yaw = std::atan2(f.tangent.y(), f.tangent.x()) + (backward ? kPi : 0.0);
  return {q.x(), q.y(), ground_z(q.x(), q.y()), yaw};
}

void City::moving_primitives(double t, const Vector2d& center, double radius,
                             std::vector<Primitive>& out) const {
  for (const MovingAgent& m : movers_) {
    double travelled = 0;
    const Placement p = mover_pose(m, t, &travelled);
    if (std::hypot(p.x - center.x(), p.y - center.y()) > radius + m.agent.length) continue;
    // One stride of a walker is about 0.75 m: the gait phase advances by pi per stride.
    emit_agent(m.agent, p, travelled / 0.75 * kPi, out);
  }
}

Eigen::Matrix4d City::lidar_pose(double t) const {
  const Street& main = streets_[0];
  const double s = ego_.s(t);
  const double d = ego_.lane_offset + ego_.sway * std::sin(ego_.sway_omega * t);
  const double d_rate = ego_.sway * ego_.sway_omega * std::cos(ego_.sway_omega * t);
  const StreetFrame f = main.at(s);
  const Vector2d q = f.p + d * f.normal;
  const double yaw = std::atan2(f.tangent.y(), f.tangent.x()) + std::atan2(d_rate, ego_.speed(t));
  // The car stands on the ground under its wheels (axles 1.4 m before and behind the sensor,
  // wheels 0.8 m to each side): its pitch and roll follow the grade and the camber, plus the
  // sway of its suspension.
  const Vector2d ahead(std::cos(yaw), std::sin(yaw)), left(-ahead.y(), ahead.x());
  const auto z_at = [&](const Vector2d& p) { return ground_z(p.x(), p.y()); };
  const double grade = (z_at(q + 1.4 * ahead) - z_at(q - 1.4 * ahead)) / 2.8;
  const double bank = (z_at(q + 0.8 * left) - z_at(q - 0.8 * left)) / 1.6;
  const double pitch = -std::atan(grade) + ego_.pitch_amp * std::sin(1.3 * t + 0.4);
  const double roll = std::atan(bank) + ego_.roll_amp * std::sin(1.7 * t + 1.1);
  Eigen::Matrix4d pose = Eigen::Matrix4d::Identity();
  pose.topLeftCorner<3, 3>() =
      (Eigen::AngleAxisd(yaw, Vector3d::UnitZ()) * Eigen::AngleAxisd(pitch, Vector3d::UnitY()) *
       Eigen::AngleAxisd(roll, Vector3d::UnitX()))
          .toRotationMatrix();
  pose.topRightCorner<3, 1>() = Vector3d(q.x(), q.y(), z_at(q) + kSensorHeight);
  return pose;
}

}  // namespace pillarseg::sim
