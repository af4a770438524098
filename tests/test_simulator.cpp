// Simulator: ray-primitive intersection by hand, the scene grid against brute force, street
// geometry and the ground layout and relief (grades, camber, curbs), the LiDAR model, and one
// written sequence (1 x 6 scans): determinism across thread counts, point counts, file order,
// beams and their dropouts, ground height, reflectance overlaps and zeros, classes, instances,
// moving agents, poses and calibration.
#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <memory>
#include <numbers>
#include <unordered_map>

#include "core/classes.hpp"
#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/io.hpp"
#include "core/parallel.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/sim/simulate.hpp"
#include "tests/support/test_support.hpp"

using namespace pillarseg;
using namespace pillarseg::sim;
namespace fs = std::filesystem;
using Eigen::Vector2d;
using Eigen::Vector3d;

namespace {

constexpr double kPi = std::numbers::pi;
constexpr uint64_t kSeed = 2024;  // data set seed of the written test sequence
constexpr int kSequence = 3;      // its id
constexpr int kScans = 6;

// The test sequence, written once (2 threads) and read back.
struct Written {
  fs::path root;
  std::unique_ptr<SequenceSimulator> sim;
  std::unique_ptr<Sequence> seq;
  std::vector<Scan> scans;
};

const Written& written() {
  static const Written w = [] {
    Written out;
    // One directory per process: CTest runs the tests of this file as parallel processes.
    out.root = fs::path(PILLARSEG_BINARY_DIR) / "test_tmp" /
               ("Simulator.shared." + std::to_string(::getpid()));
    fs::remove_all(out.root);
    const int threads = num_threads();
    set_num_threads(2);
    SimulateOptions options;
    options.out = out.root;
    options.sequences = 1;
    options.scans = kScans;
    options.seed = kSeed;
    options.first_sequence = kSequence;
    simulate(options);
    set_num_threads(threads);
    out.sim = std::make_unique<SequenceSimulator>(sequence_seed(kSeed, kSequence), kScans);
    out.seq = std::make_unique<Sequence>(out.root, kSequence);
    for (size_t i = 0; i < out.seq->size(); ++i) out.scans.push_back(out.seq->load(i));
    return out;
  }();
  return w;
}

Vector3d to_world(const Pose& pose, const Point& p) {
  return (pose * Eigen::Vector4d(p.x, p.y, p.z, 1.0)).head<3>();
}

double median(std::vector<double> v) {
  if (v.empty()) return std::nan("");
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
  return v[v.size() / 2];
}

// A noiseless sensor (no dropout, outliers or range noise) of azimuth_steps pulses a revolution,
// far from every street of the city: at (kX, kY) on its terrain, kSensorHeight above it; the
// scenes around it are built by hand.
struct RemoteSensor {
  static constexpr double kX = 1e6, kY = 1e6;
  LidarModel lidar;
  double ground;  // the terrain's height under the sensor
  Pose pose = Pose::Identity();

  RemoteSensor(const City& city, int azimuth_steps)
      : lidar(LidarModel::hdl64e(azimuth_steps)), ground(city.ground_z(kX, kY)) {
    lidar.dropout = 0.0;
    lidar.outlier_rate = 0.0;
    lidar.range_noise = 0.0;
    pose.topRightCorner<3, 1>() = Vector3d(kX, kY, ground + kSensorHeight);
  }
  // A building wall 1 m thick and 10 m tall facing the sensor along x, its centre dx ahead
  // (behind where negative), half_width to each side of the sensor's line.
  Primitive wall(double dx, double half_width, float albedo) const {
    return make_box({kX + dx, kY, ground + 5}, {0.5, half_width, 5}, 0.0,
                    label_word(raw::kBuilding, 0), albedo);
  }
};

// Histogram overlap of two samples in [0, 1] (50 bins): 1 for equal distributions.
double overlap(const std::vector<double>& a, const std::vector<double>& b) {
  std::array<double, 50> ha{}, hb{};
  for (double v : a) ha[static_cast<size_t>(std::clamp(v * 50.0, 0.0, 49.0))] += 1.0 / a.size();
  for (double v : b) hb[static_cast<size_t>(std::clamp(v * 50.0, 0.0, 49.0))] += 1.0 / b.size();
  double sum = 0;
  for (size_t i = 0; i < 50; ++i) sum += std::min(ha[i], hb[i]);
  return sum;
}

// Distance of each query to the plane fitted to the points of `cloud` within 0.4 m of it (the
// queries with fewer than 6 such points are left out): how far the query lies off the surface
// the cloud samples, whatever the two samplings' spacing.
std::vector<double> plane_distances(const std::vector<Vector3d>& cloud,
                                    const std::vector<Vector3d>& queries) {
  const double cell = 0.4;
  const auto key = [](int64_t x, int64_t y, int64_t z) {
    return (x * 73856093) ^ (y * 19349663) ^ (z * 83492791);
  };
  const auto idx = [&](double v) { return static_cast<int64_t>(std::floor(v / cell)); };
  std::unordered_multimap<int64_t, size_t> hash;
  for (size_t i = 0; i < cloud.size(); ++i)
    hash.emplace(key(idx(cloud[i].x()), idx(cloud[i].y()), idx(cloud[i].z())), i);
  std::vector<double> out;
  std::vector<Vector3d> near;
  for (const Vector3d& q : queries) {
    near.clear();
    for (int64_t dx = -1; dx <= 1; ++dx)
      for (int64_t dy = -1; dy <= 1; ++dy)
        for (int64_t dz = -1; dz <= 1; ++dz) {
          const auto range =
              hash.equal_range(key(idx(q.x()) + dx, idx(q.y()) + dy, idx(q.z()) + dz));
          for (auto it = range.first; it != range.second; ++it)
            if ((cloud[it->second] - q).norm() < cell) near.push_back(cloud[it->second]);
        }
    if (near.size() < 6) continue;
    Vector3d mean = Vector3d::Zero();
    for (const Vector3d& p : near) mean += p;
    mean /= static_cast<double>(near.size());
    Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
    for (const Vector3d& p : near) cov += (p - mean) * (p - mean).transpose();
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver(cov);
    out.push_back(std::abs(solver.eigenvectors().col(0).dot(q - mean)));
  }
  return out;
}

Primitive random_primitive(Rng& rng) {
  Vector3d c, h;  // one draw per statement, so the scene does not depend on the compiler
  for (int a = 0; a < 3; ++a) c[a] = a < 2 ? rng.uniform(-20, 20) : rng.uniform(0, 4);
  for (int a = 0; a < 3; ++a) h[a] = rng.uniform(0.05, 3);
  const double yaw = rng.uniform(-kPi, kPi);
  switch (rng.uniform_int(3)) {
    case 0:
      return make_box(c, h, yaw, 10, 0.5f);
    case 1:
      return make_cylinder(c.x(), c.y(), c.z() - h.z(), c.z() + h.z(), h.x(), 80, 0.3f);
    default:
      return make_ellipsoid(c, h, yaw, 70, 0.4f);
  }
}

}  // namespace

// ---- primitives and the scene grid --------------------------------------------------------

TEST(SimScene, IntersectsBoxCylinderEllipsoidByHand) {
  Hit h;
  // A box 2 x 4 x 6 turned by 90 deg: its local y axis (half 2) lies along world x.
  const Primitive box = make_box({0, 0, 0}, {1, 2, 3}, kPi / 2, 10, 0.5f);
  ASSERT_TRUE(intersect(box, {{10, 0, 0}, {-1, 0, 0}}, 0, 100, &h));
  EXPECT_NEAR(h.t_enter, 8.0, 1e-12);
  EXPECT_NEAR(h.t_exit, 12.0, 1e-12);
  EXPECT_NEAR(h.normal.x(), 1.0, 1e-12);
  ASSERT_TRUE(intersect(box, {{0, 10, 0}, {0, -1, 0}}, 0, 100, &h));
  EXPECT_NEAR(h.t_enter, 9.0, 1e-12);
  EXPECT_FALSE(intersect(box, {{10, 0, 0}, {-1, 0, 0}}, 0, 7.9, &h)) << "beyond t_max";
  EXPECT_FALSE(intersect(box, {{0, 0, 0}, {1, 0, 0}}, 0, 100, &h))
      << "a ray from inside does not hit";
  EXPECT_FALSE(intersect(box, {{10, 0, 3.5}, {-1, 0, 0}}, 0, 100, &h)) << "passes over";

  const Primitive cyl = make_cylinder(1, 1, 0, 2, 0.5, 80, 0.3f);
  ASSERT_TRUE(intersect(cyl, {{5, 1, 1}, {-1, 0, 0}}, 0, 100, &h));
  EXPECT_NEAR(h.t_enter, 3.5, 1e-12);
  EXPECT_NEAR(h.normal.x(), 1.0, 1e-12);
  ASSERT_TRUE(intersect(cyl, {{1.2, 1, 10}, {0, 0, -1}}, 0, 100, &h))
      << "vertical ray onto the top cap";
  EXPECT_NEAR(h.t_enter, 8.0, 1e-12);
  EXPECT_NEAR(h.normal.z(), 1.0, 1e-12);
  EXPECT_FALSE(intersect(cyl, {{1.6, 1, 10}, {0, 0, -1}}, 0, 100, &h)) << "vertical ray beside it";

  const Primitive ell = make_ellipsoid({0, 0, 1}, {2, 1, 0.5}, 0.0, 70, 0.4f);
  ASSERT_TRUE(intersect(ell, {{5, 0, 1}, {-1, 0, 0}}, 0, 100, &h));
  EXPECT_NEAR(h.t_enter, 3.0, 1e-12);
  EXPECT_NEAR(h.t_exit, 7.0, 1e-12);
  ASSERT_TRUE(intersect(ell, {{0, 0, 5}, {0, 0, -1}}, 0, 100, &h));
  EXPECT_NEAR(h.t_enter, 3.5, 1e-12);
  EXPECT_NEAR(h.normal.z(), 1.0, 1e-12);
  // The same ellipsoid turned by 90 deg is 1 m (not 2 m) deep along x.
  const Primitive turned = make_ellipsoid({0, 0, 1}, {2, 1, 0.5}, kPi / 2, 70, 0.4f);
  ASSERT_TRUE(intersect(turned, {{5, 0, 1}, {-1, 0, 0}}, 0, 100, &h));
  EXPECT_NEAR(h.t_enter, 4.0, 1e-12);
}

TEST(SimScene, FootprintBoundsTheShape) {
  const Footprint f = footprint(make_box({1, 2, 3}, {2, 1, 0.5}, kPi / 2, 0, 0.f));
  EXPECT_NEAR(f.x0, 0.0, 1e-12);
  EXPECT_NEAR(f.x1, 2.0, 1e-12);
  EXPECT_NEAR(f.y0, 0.0, 1e-12);
  EXPECT_NEAR(f.y1, 4.0, 1e-12);
  EXPECT_NEAR(f.z0, 2.5, 1e-12);
  EXPECT_NEAR(f.z1, 3.5, 1e-12);
  const Footprint e = footprint(make_ellipsoid({0, 0, 0}, {2, 1, 1}, kPi / 4, 0, 0.f));
  EXPECT_NEAR(e.x1, std::sqrt(2.5), 1e-12);  // hypot(2 cos 45, 1 sin 45)
}

TEST(SimScene, GridTraceEqualsBruteForce) {
  Rng rng(5);
  std::vector<Primitive> prims;
  for (int i = 0; i < 300; ++i) prims.push_back(random_primitive(rng));
  for (double cell : {0.7, 2.0, 9.0}) {
    const SceneGrid grid(prims, cell);
    int hits = 0;
    for (int r = 0; r < 4000; ++r) {
      Ray ray;
      Vector3d d;
      for (int a = 0; a < 3; ++a) ray.origin[a] = a < 2 ? rng.uniform(-30, 30) : rng.uniform(-1, 6);
      for (int a = 0; a < 3; ++a) d[a] = (a < 2 ? 1.0 : 0.3) * rng.normal();
      if (r % 10 == 0) d = Vector3d(0, 0, -1);                    // vertical
      if (r % 10 == 1) d = Vector3d(r % 20 == 1 ? 1 : -1, 0, 0);  // along a grid axis
      ray.dir = d.normalized();
      const double t_min = r % 3 == 0 ? 0.0 : rng.uniform(0, 10), t_max = rng.uniform(5, 80);
      Hit a, b;
      const bool fa = grid.trace(ray, t_min, t_max, &a),
                 fb = trace_brute_force(prims, ray, t_min, t_max, &b);
      ASSERT_EQ(fa, fb) << "ray " << r << " cell " << cell;
      if (!fa) continue;
      ++hits;
      EXPECT_EQ(a.primitive, b.primitive) << "ray " << r;
      EXPECT_EQ(a.t_enter, b.t_enter) << "ray " << r;
    }
    EXPECT_GT(hits, 400) << "the random rays must hit often enough to test something";
  }
  EXPECT_FALSE(SceneGrid({}, 2.0).trace({{0, 0, 0}, {1, 0, 0}}, 0, 100, nullptr)) << "empty scene";
  EXPECT_THROW(SceneGrid(prims, 0.0), Error);
}

// ---- streets and the city -----------------------------------------------------------------

TEST(SimStreet, ProjectsOntoStraightAndCurvedCentreLines) {
  std::vector<Vector2d> line;
  for (int i = 0; i <= 50; ++i) line.emplace_back(2.0 * i, 0.0);
  Street straight(line);
  EXPECT_DOUBLE_EQ(straight.length(), 100.0);
  double s = 0, d = 0;
  straight.project({50.3, 3.0}, 0, &s, &d);
  EXPECT_NEAR(s, 50.3, 1e-12);
  EXPECT_NEAR(d, 3.0, 1e-12);
  straight.project({20.0, -4.0}, 49, &s, &d);  // a far hint walks back
  EXPECT_NEAR(s, 20.0, 1e-12);
  EXPECT_NEAR(d, -4.0, 1e-12);
  straight.project({105.0, 1.0}, 10, &s, &d);
  EXPECT_NEAR(s, 105.0, 1e-12) << "extrapolated beyond the end";
  EXPECT_EQ(straight.zone(s, d), Zone::kOutside);
  const StreetFrame f = straight.at(25.0);
  EXPECT_NEAR(f.p.x(), 25.0, 1e-12);
  EXPECT_NEAR(f.normal.y(), 1.0, 1e-12);

  // Quarter circle of radius 50, counter-clockwise: left of it is the centre.
  std::vector<Vector2d> arc;
  for (int i = 0; i <= 200; ++i)
    arc.emplace_back(50 * std::cos(i * kPi / 400), 50 * std::sin(i * kPi / 400));
  Street curved(arc);
  for (double theta : {0.2, 0.7, 1.3}) {
    curved.project({45 * std::cos(theta), 45 * std::sin(theta)}, 0, &s, &d);
    EXPECT_NEAR(s, 50 * theta, 0.02);
    EXPECT_NEAR(d, 5.0, 0.01);
  }
}

TEST(SimStreet, ZonesFollowTheCrossSection) {
  std::vector<Vector2d> line;
  for (int i = 0; i <= 50; ++i) line.emplace_back(2.0 * i, 0.0);
  Street st(line);
  StreetSide& right = st.sides[0];
  right.bike = 1.5, right.parking = 2.0, right.lawn = 1.0, right.sidewalk = 3.0, right.front = 4.0;
  right.set_edges(3.0, 20.0);
  st.sides[1] = right;
  EXPECT_DOUBLE_EQ(right.e_curb, 6.5);
  EXPECT_DOUBLE_EQ(right.e_walk, 10.5);
  const std::vector<std::pair<double, Zone>> expected = {
      {0.5, Zone::kRoad},  {3.5, Zone::kBikeLane}, {5.0, Zone::kParking},
      {7.0, Zone::kLawn},  {9.0, Zone::kSidewalk}, {12.0, Zone::kFront},
      {30.0, Zone::kBack}, {40.0, Zone::kOutside}};
  for (const auto& [a, zone] : expected) {
    EXPECT_EQ(st.zone(50.0, -a), zone) << "right at " << a;
    EXPECT_EQ(st.zone(50.0, a), zone) << "left at " << a;
  }
  EXPECT_EQ(st.zone(-0.1, 0.0), Zone::kOutside);
}

TEST(SimCity, GroundFollowsTheStreetBandsAndHeights) {
  const City city = City::generate(11, 50);
  const Street& main = city.streets()[0];
  ASSERT_GE(city.streets().size(), 2u) << "side streets";
  int checked = 0;
  for (double s = city.ego().s0; s < city.ego().s0 + 150.0; s += 1.7) {
    for (int side = 0; side < 2; ++side) {
      const StreetSide& ss = main.sides[static_cast<size_t>(side)];
      const double sign = side == 0 ? -1.0 : 1.0;
      const auto sample_at = [&](double a) {
        const Vector2d q = main.point(s, sign * a);
        std::array<StreetCoord, 8> near;
        const int n = city.locate(q.x(), q.y(), &near);
        bool alone = true;
        for (int i = 0; i < n; ++i) {
          const StreetCoord& c = near[static_cast<size_t>(i)];
          alone = alone && (c.street == 0 || c.zone >= Zone::kBack);
        }
        return std::pair{city.ground_at(q.x(), q.y()), alone};
      };
      // Only where no other street comes closer than its backyards (away from intersections).
      const auto [road, alone] = sample_at(0.5 * ss.e_road);
      if (!alone) continue;
      EXPECT_FALSE(road.raised);
      EXPECT_TRUE(road.label == raw::kRoad || road.label == raw::kLaneMarking) << road.label;
      const auto [walk, alone_walk] = sample_at(ss.e_lawn + 0.5 * ss.sidewalk);
      if (alone_walk) {
        EXPECT_TRUE(walk.raised);
        EXPECT_EQ(walk.label, raw::kSidewalk);
      }
      if (ss.parking > 0) {
        const auto [park, alone_park] = sample_at(ss.e_bike + 0.5 * ss.parking);
        if (alone_park) {
          EXPECT_FALSE(park.raised);
          EXPECT_TRUE(park.label == raw::kParking || park.label == raw::kRoad ||
                      park.label == raw::kLaneMarking)
              << park.label;
        }
      }
      if (ss.lawn > 0.3) {
        const auto [lawn, alone_lawn] = sample_at(ss.e_curb + 0.5 * ss.lawn);
        if (alone_lawn) {
          EXPECT_EQ(lawn.label, raw::kTerrain);
        }
      }
      ++checked;
    }
  }
  EXPECT_GT(checked, 80);
  const GroundSample far = city.ground_at(1e7, 1e7);
  EXPECT_TRUE(far.raised) << "far outside: terrain";
  EXPECT_EQ(far.label, raw::kTerrain);
}

TEST(SimCity, GroundHasGradesCamberAndCurbs) {
  const City city = City::generate(11, 50);
  const Street& main = city.streets()[0];
  const Relief& relief = city.relief();
  EXPECT_GE(city.curb_height(), 0.10);
  EXPECT_LE(city.curb_height(), 0.16);
  // Along 300 m of the main street's centre line the road rises and falls by decimetres.
  double low = 1e9, high = -1e9;
  std::vector<double> curbs, cambers;
  for (double s = city.ego().s0 - 150.0; s < city.ego().s0 + 150.0; s += 2.0) {
    const Vector2d c = main.point(s, 0.0);
    const double z = city.ground_z(c.x(), c.y());
    low = std::min(low, z), high = std::max(high, z);
    for (int side = 0; side < 2; ++side) {
      const StreetSide& ss = main.sides[static_cast<size_t>(side)];
      const double sign = side == 0 ? -1.0 : 1.0;
      // The road at the curb against the sidewalk 0.3 m behind the lawn (if any), which rises
      // from the curb's top at walk_slope.
      const Vector2d road = main.point(s, sign * (ss.e_curb - 0.05));
      const Vector2d walk = main.point(s, sign * (ss.e_lawn + 0.3));
      const GroundSample g_road = city.ground_at(road.x(), road.y());
      const GroundSample g_walk = city.ground_at(walk.x(), walk.y());
      if (g_road.raised || g_walk.label != raw::kSidewalk) continue;  // a junction
      // Heights above the street's grade (no hills before the back of the sidewalk).
      const double walk_z = g_walk.z - relief.grade_at(walk.x(), walk.y());
      const double road_z = g_road.z - relief.grade_at(road.x(), road.y());
      // The camber falls over the first 4 m: a road narrower than that ends higher.
      const double camber_left = relief.camber * std::max(0.0, 4.0 - (ss.e_curb - 0.05));
      curbs.push_back(walk_z - road_z - relief.walk_slope * (ss.e_lawn + 0.3 - ss.e_curb) +
                      camber_left);
      // The camber: the lane beside the centre line lies higher than the road at the curb.
      const Vector2d lane = main.point(s, sign * 1.0);
      cambers.push_back(city.ground_z(lane.x(), lane.y()) - g_road.z);
    }
  }
  EXPECT_GT(high - low, 0.1) << "the street's grade varies";
  ASSERT_GT(curbs.size(), 100u);
  // Curb height, give or take the paving's small bumps (a quarter of the terrain's, at most
  // 1.5 times that on each side) and the camber's 5 cm of road.
  for (double d : curbs) {
    EXPECT_GT(d, city.curb_height() - 0.75 * relief.roughness - 0.05 * relief.camber)
        << "a curb between road and sidewalk";
    EXPECT_LT(d, city.curb_height() + 0.75 * relief.roughness);
  }
  EXPECT_NEAR(median(curbs), city.curb_height(), 0.02);
  // At least 2 m of the camber's fall from 1 m off the centre line to the curb.
  EXPECT_GT(median(cambers), 2.0 * relief.camber) << "the road falls towards the curb";
  // The ground is continuous away from curbs: neighbours 5 cm apart differ by little.
  int64_t steps = 0, samples = 0;
  const Vector2d o = main.point(city.ego().s0, 0.0);
  for (double x = -60; x < 60; x += 0.37)
    for (double y = -60; y < 60; y += 3.1) {
      const GroundSample a = city.ground_at(o.x() + x, o.y() + y);
      const GroundSample b = city.ground_at(o.x() + x + 0.05, o.y() + y);
      ++samples;
      if (a.raised == b.raised) steps += std::abs(a.z - b.z) > 0.03;
    }
  EXPECT_LT(steps, samples / 200) << steps << " steps of more than 3 cm in " << samples;
}

TEST(SimStreet, YardsFallAwayFromTheSidewalkAndLevelOff) {
  StreetSide side;
  side.sidewalk = 3.0, side.front = 4.0;
  side.set_edges(3.0, 25.0);  // e_walk 6, e_back 35
  side.terrain_offset = -0.02, side.yard_drop = 0.4, side.yard_slope = 0.04;
  // -0.02 - 0.4 (1 - exp(-0.04 t / 0.4)): flush at the sidewalk, 4 cm per metre there,
  // -0.02 - 0.4 (1 - e^-1) = -0.2728 10 m out, -0.42 far out.
  EXPECT_NEAR(side.yard_offset(6.0), -0.02, 1e-12);
  EXPECT_NEAR(side.yard_offset(5.0), -0.02, 1e-12) << "on the sidewalk: its level";
  EXPECT_NEAR((side.yard_offset(6.001) - side.yard_offset(6.0)) / 0.001, -0.04, 1e-4);
  EXPECT_NEAR(side.yard_offset(16.0), -0.02 - 0.4 * (1 - std::exp(-1.0)), 1e-12);
  EXPECT_NEAR(side.yard_offset(1000.0), -0.42, 1e-9);
  side.yard_drop = -0.1;  // rising instead, levelling off 0.1 m up
  EXPECT_NEAR(side.yard_offset(16.0), -0.02 + 0.1 * (1 - std::exp(-4.0)), 1e-12);
  side.yard_drop = 0;
  EXPECT_DOUBLE_EQ(side.yard_offset(16.0), -0.02);
}

// The cross-section measured on the real labelled scan (docs/simulator.md): the sidewalk at the
// curb (no grass touches the road), grass level with the paving at the back of the sidewalk and
// falling away further out on most sides, and paved paths through the grass.
TEST(SimCity, SidewalkAtTheCurbGrassFallingAwayAndPathsThroughIt) {
  int sides = 0, lawns = 0, falling = 0, open_lots = 0, lots = 0, paths = 0, far = 0;
  std::vector<double> flush, fall10;
  int64_t path_checked = 0;
  for (uint64_t seed : {1, 2, 3, 4, 5, 6}) {
    const City city = City::generate(seed, 20);
    const Relief& relief = city.relief();
    const Street& main = city.streets()[0];
    for (const Street& st : city.streets())
      for (const StreetSide& ss : st.sides) {
        ++sides;
        lawns += ss.lawn > 0;
        falling += ss.yard_drop > 0;
        EXPECT_GE(ss.terrain_offset, -0.06);
        EXPECT_LE(ss.terrain_offset, 0.02);
        for (const Lot& lot : ss.lots) {
          ++lots;
          open_lots += lot.open_green;
          far += lot.far_setback > 0;
          if (lot.open_green) {
            EXPECT_FALSE(lot.building);
          }
        }
      }
    // The main street's sides, away from other streets: heights above the grade and the hills
    // (weighted as ground_at does, by the distance behind the sidewalk over kHillFade).
    // A sample at arc length s and distance a on a side of the main street; *alone stays true
    // where no other street's band reaches.
    const auto at = [&](int side, double s, double a, bool* alone) {
      const StreetSide& ss = main.sides[static_cast<size_t>(side)];
      const Vector2d q = main.point(s, side == 0 ? -a : a);
      std::array<StreetCoord, 8> near;
      const int n = city.locate(q.x(), q.y(), &near);
      for (int i = 0; i < n; ++i) {
        const StreetCoord& c = near[static_cast<size_t>(i)];
        *alone = *alone && (c.street == 0 || c.zone == Zone::kOutside);
      }
      GroundSample g = city.ground_at(q.x(), q.y());
      const double w = std::clamp((a - ss.e_walk) / Relief::kHillFade, 0.0, 1.0);
      g.z -= relief.grade_at(q.x(), q.y()) + w * relief.hills_at(q.x(), q.y());
      return g;
    };
    for (double s = 20.0; s < main.length() - 20.0; s += 1.3) {
      for (int side = 0; side < 2; ++side) {
        const StreetSide& ss = main.sides[static_cast<size_t>(side)];
        bool alone = true;
        const GroundSample curb = at(side, s, ss.e_curb + 0.3, &alone);
        const GroundSample back = at(side, s, ss.e_walk - 0.1, &alone);
        const GroundSample yard = at(side, s, ss.e_walk + 0.1, &alone);
        const GroundSample out = at(side, s, ss.e_walk + 10.0, &alone);
        if (!alone) continue;
        if (ss.lawn == 0) {
          EXPECT_EQ(curb.label, raw::kSidewalk) << "sidewalk at the curb";
        }
        if (yard.label == raw::kTerrain && out.label == raw::kTerrain) {
          flush.push_back(yard.z - back.z - ss.terrain_offset);
          if (ss.yard_drop > 0) fall10.push_back(out.z - back.z);
        }
        // Paths across open greens: sidewalk at the yard's level, grass beside them.
        const auto it = std::upper_bound(ss.lots.begin(), ss.lots.end(), s,
                                         [](double v, const Lot& lot) { return v < lot.s1; });
        if (it == ss.lots.end() || !it->open_green || it->path_depth <= 0 ||
            std::abs(s - it->path_s) > 0.65 || it->path_s + it->path_half + 1.0 > it->s1)
          continue;
        const GroundSample on = at(side, s, ss.e_walk + 1.5, &alone);
        const GroundSample beside =
            at(side, it->path_s + it->path_half + 0.6, ss.e_walk + 1.5, &alone);
        if (!alone) continue;
        EXPECT_EQ(on.label, raw::kSidewalk) << "a path through the green";
        EXPECT_EQ(beside.label, raw::kTerrain) << "grass beside the path";
        EXPECT_NEAR(on.z, beside.z, 0.12) << "the path at the grass's level";
        ++path_checked;
      }
    }
    for (const Street& st : city.streets())
      for (const StreetSide& ss : st.sides)
        for (const Lot& lot : ss.lots) paths += lot.path_depth > 0;
  }
  // Tree lawns on 15% of the sides, yards falling away on 70%, open greens on half of the
  // lots without a building (about 15% of all lots), 70% of them with a building behind.
  ASSERT_GT(sides, 60);
  EXPECT_GT(lawns, sides * 5 / 100);
  EXPECT_LT(lawns, sides * 30 / 100);
  EXPECT_GT(falling, sides / 2);
  EXPECT_LT(falling, sides * 85 / 100);
  EXPECT_GT(open_lots, lots / 12);
  EXPECT_LT(open_lots, lots / 4);
  EXPECT_GT(far, open_lots / 3) << "far buildings behind the open greens";
  EXPECT_GT(paths, 0);
  EXPECT_GT(path_checked, 0);
  // Grass meets the sidewalk at its level: the median step is the side's offset, give or take
  // the grass's bumps (mostly cancelled by the median).
  ASSERT_GT(flush.size(), 100u);
  EXPECT_NEAR(median(flush), 0.0, 0.03);
  // 10 m out, falling sides lie 0.08-0.6 m (a 1-6% fall levelling off 0.2-0.6 m down) below
  // the back of the sidewalk.
  ASSERT_GT(fall10.size(), 50u);
  EXPECT_LT(median(fall10), -0.08);
  EXPECT_GT(median(fall10), -0.7);
  for (double z : fall10) EXPECT_LT(z, 0.15) << "a falling side does not rise";
}

TEST(SimCity, GrassALittleBrighterThanPavingBothFinelyTextured) {
  // The ground's albedo 0-30 m across the main street, per city: grass 1-1.32 times the
  // paving at the median (the real labelled scan: 1.16), and both with a texture of +-20%
  // (the middle 60% of their albedos within 0.32 of the median: 0.24 for +-20%, 0.42 for the
  // asphalt's +-35%; dark patches are 8% of the cells and stay outside it).
  const auto quantile = [](std::vector<double> v, double q) {
    std::sort(v.begin(), v.end());
    return v[static_cast<size_t>(q * static_cast<double>(v.size() - 1))];
  };
  int cities = 0;
  for (uint64_t seed : {1, 2, 3, 4, 5, 6, 7, 8}) {
    const City city = City::generate(seed, 20);
    const Street& main = city.streets()[0];
    std::map<uint32_t, std::vector<double>> albedo;
    for (double s = city.ego().s0; s < city.ego().s0 + 120.0; s += 0.37)
      for (double d = -30.0; d <= 30.0; d += 0.29) {
        const Vector2d q = main.point(s, d);
        const GroundSample g = city.ground_at(q.x(), q.y());
        albedo[g.label].push_back(g.albedo);
      }
    const std::vector<double>& walk = albedo[raw::kSidewalk];
    const std::vector<double>& grass = albedo[raw::kTerrain];
    if (walk.size() < 500 || grass.size() < 500) continue;
    ++cities;
    const double walk50 = quantile(walk, 0.5), grass50 = quantile(grass, 0.5);
    EXPECT_GE(grass50 / walk50, 0.97) << "seed " << seed;
    EXPECT_LE(grass50 / walk50, 1.36) << "seed " << seed;
    for (const std::vector<double>* v : {&walk, &grass}) {
      const double spread = (quantile(*v, 0.8) - quantile(*v, 0.2)) / quantile(*v, 0.5);
      EXPECT_GT(spread, 0.15) << "seed " << seed << ": textured";
      EXPECT_LT(spread, 0.32) << "seed " << seed;
    }
  }
  EXPECT_GE(cities, 6);
}

TEST(SimCity, HasSideStreetsEvery100mAndDiffersBySeed) {
  const City a = City::generate(3, 200), b = City::generate(3, 200), c = City::generate(4, 200);
  ASSERT_EQ(a.static_scene().size(), b.static_scene().size());
  EXPECT_EQ(a.static_scene().primitives()[100].center, b.static_scene().primitives()[100].center);
  EXPECT_EQ(a.movers().size(), b.movers().size());
  EXPECT_NE(a.streets()[0].points.back(), c.streets()[0].points.back())
      << "another seed, another street";
  const Street& main = a.streets()[0];
  // Where the side streets leave the main street.
  std::vector<double> junctions;
  for (size_t k = 1; k < a.streets().size(); ++k) {
    double s = 0, d = 0;
    main.project(a.streets()[k].points.front(), main.segments() / 2, &s, &d);
    EXPECT_NEAR(d, 0.0, 1e-6);
    junctions.push_back(s);
  }
  EXPECT_GE(static_cast<double>(junctions.size()), main.length() / 120.0)
      << junctions.size() << " side streets on " << main.length() << " m";
  EXPECT_THROW(City::generate(1, 0), Error);
}

TEST(SimCity, EgoDrivesAtCitySpeedsOnItsLane) {
  const City city = City::generate(8, 100);
  for (int i = 0; i + 1 < 100; ++i) {
    const Pose a = city.lidar_pose(i * kScanPeriod), b = city.lidar_pose((i + 1) * kScanPeriod);
    const double speed = (b.topRightCorner<3, 1>() - a.topRightCorner<3, 1>()).norm() / kScanPeriod;
    EXPECT_GE(speed, 4.8);
    EXPECT_LE(speed, 12.2);
    EXPECT_NEAR(a(2, 3), city.ground_z(a(0, 3), a(1, 3)) + kSensorHeight, 1e-9);
    // The car pitches with the grade under its axles (1.4 m ahead and behind), within 0.1 deg.
    const Vector3d x_axis = a.topLeftCorner<3, 3>().col(0);
    const Vector2d ahead = x_axis.head<2>().normalized(), at(a(0, 3), a(1, 3));
    const Vector2d front = at + 1.4 * ahead, back = at - 1.4 * ahead;
    const double grade =
        (city.ground_z(front.x(), front.y()) - city.ground_z(back.x(), back.y())) / 2.8;
    EXPECT_NEAR(std::asin(x_axis.z()), std::atan(grade), 0.1 * kPi / 180) << "scan " << i;
    const GroundSample under = city.ground_at(a(0, 3), a(1, 3));
    EXPECT_FALSE(under.raised) << "the ego drives on the road";
  }
}

// ---- the LiDAR model ----------------------------------------------------------------------

TEST(SimLidar, Hdl64eBeamTableAndPulseCount) {
  const LidarModel m = LidarModel::hdl64e(2000);
  ASSERT_EQ(m.beams(), 64);
  EXPECT_DOUBLE_EQ(m.elevation_deg.front(), 2.0);
  EXPECT_NEAR(m.elevation_deg[31], -8.33, 1e-12);
  EXPECT_NEAR(m.elevation_deg[32], -8.83, 1e-12);
  EXPECT_NEAR(m.elevation_deg.back(), -24.9, 1e-12);
  for (int b = 1; b < 64; ++b)
    EXPECT_LT(m.elevation_deg[static_cast<size_t>(b)], m.elevation_deg[static_cast<size_t>(b) - 1]);
  // Denser upper block (1/3 deg) than lower block (about 1/2 deg), as on the HDL-64E.
  EXPECT_NEAR(m.elevation_deg[0] - m.elevation_deg[1], 10.33 / 31, 1e-12);
  EXPECT_NEAR(m.elevation_deg[32] - m.elevation_deg[33], 16.07 / 31, 1e-12);
  EXPECT_NEAR(m.azimuth(0), -kPi + kPi / 2000, 1e-12);
  const int steps = LidarModel::azimuth_steps_for(120000);
  EXPECT_GE(steps, 1800);
  EXPECT_LE(steps, 2400);
  EXPECT_THROW(LidarModel::azimuth_steps_for(5000), Error);
  EXPECT_THROW(LidarModel::hdl64e(100), Error);
}

TEST(SimLidar, HillyGroundAndAWallByHand) {
  // A city far away: the sensor stands on its terrain (hills, grades, bumps), with one wall
  // 10 m ahead.
  const City city = City::generate(1, 1);
  const RemoteSensor sensor(city, 720);
  const SimScan scan =
      cast_scan(sensor.lidar, city, SceneGrid({sensor.wall(10.5, 20, 0.4f)}, 2.0), sensor.pose, 1);
  int on_wall = 0, on_ground = 0;
  std::vector<double> heights;
  for (size_t i = 0; i < scan.points.size(); ++i) {
    const Point& p = scan.points[i];
    if (scan.labels[i] == raw::kBuilding) {
      ++on_wall;
      EXPECT_NEAR(p.x, 10.0, 1e-4);
    } else {
      ASSERT_EQ(scan.labels[i], raw::kTerrain);
      ++on_ground;
      // On the height field, or in the grass's top 7 cm above it (the march stops within 2 mm
      // of the surface, below it).
      const double surface = city.ground_z(RemoteSensor::kX + p.x, RemoteSensor::kY + p.y) -
                             sensor.ground - kSensorHeight;
      EXPECT_GE(p.z, surface - 3e-3);
      EXPECT_LE(p.z, surface + 0.07 + 1e-4);
      heights.push_back(p.z);
    }
    EXPECT_GE(p.r, 0.f);
    EXPECT_LE(p.r, 1.f);
  }
  EXPECT_GT(on_wall, 500);
  EXPECT_GT(on_ground, 10000);
  std::sort(heights.begin(), heights.end());
  EXPECT_GT(heights[heights.size() * 95 / 100] - heights[heights.size() * 5 / 100], 0.1)
      << "the terrain is not flat";
  // No return from inside the ego body box.
  for (const Point& p : scan.points)
    EXPECT_FALSE(p.x > sensor.lidar.body_min.x() && p.x < sensor.lidar.body_max.x() &&
                 std::abs(p.y) < sensor.lidar.body_max.y() && p.z < sensor.lidar.body_max.z());
}

TEST(SimLidar, IntensityFallsWithTheRangeAsInARealScan) {
  // Two walls of one albedo facing the sensor, 8 m ahead and 40 m behind it: beyond 12 m the
  // intensity is divided by 1 + ((range - 12) / 25)^2, so the far wall reads 0.44 of the near
  // one (the real labelled scan's sidewalk, terrain and vegetation: 0.5-0.6 at 30-60 m, non-zero
  // returns), and its returns (0.22 against a floor of 0.12 there) do not read 0.
  const City city = City::generate(1, 1);
  const RemoteSensor sensor(city, 1440);
  const SceneGrid walls({sensor.wall(8.5, 4, 0.5f), sensor.wall(-40.5, 20, 0.5f)}, 2.0);
  const SimScan scan = cast_scan(sensor.lidar, city, walls, sensor.pose, 1);
  double near_sum = 0, far_sum = 0;
  int near = 0, far = 0, far_zero = 0;
  for (size_t i = 0; i < scan.points.size(); ++i) {
    const Point& p = scan.points[i];
    if (scan.labels[i] != raw::kBuilding || std::abs(p.y) > 0.15 * std::abs(p.x)) continue;
    if (p.x > 0) {
      near_sum += p.r, ++near;
    } else {
      far_sum += p.r, ++far, far_zero += p.r == 0.f;
    }
  }
  ASSERT_GT(near, 100);
  ASSERT_GT(far, 30);
  const double ratio = (far_sum / far) / (near_sum / near);
  EXPECT_GT(ratio, 0.38);
  EXPECT_LT(ratio, 0.5);
  EXPECT_LT(far_zero, far / 10);
}

// ---- the written sequence -----------------------------------------------------------------

TEST(SimSequence, ReadsBackWithCountsInRange) {
  const Written& w = written();
  ASSERT_EQ(w.seq->size(), static_cast<size_t>(kScans));
  ASSERT_TRUE(w.seq->has_poses());
  for (size_t i = 0; i < w.scans.size(); ++i) {
    const Scan& s = w.scans[i];
    EXPECT_EQ(s.labels.size(), s.points.size());
    EXPECT_EQ(s.dropped_nonfinite, 0u);
    EXPECT_GE(s.points.size(), 90000u) << "scan " << i;
    EXPECT_LE(s.points.size(), 150000u) << "scan " << i;
    EXPECT_EQ(w.seq->frame(i), static_cast<int>(i));
  }
}

TEST(SimSequence, ByteIdenticalWhateverTheThreadsAndDifferentOtherwise) {
  const Written& w = written();
  const fs::path dir = test::temp_dir();
  const int threads = num_threads();
  set_num_threads(1);
  SimulateOptions options;
  options.out = dir;
  options.scans = kScans;
  options.seed = kSeed;
  options.first_sequence = kSequence;
  simulate(options);
  set_num_threads(threads);
  const fs::path a = w.root / "sequences" / "03", b = dir / "sequences" / "03";
  for (const std::string name :
       {"poses.txt", "calib.txt", "velodyne/000000.bin", "labels/000000.label",
        "velodyne/000005.bin", "labels/000005.label"})
    EXPECT_EQ(read_file_bytes(a / name), read_file_bytes(b / name)) << name;
  // Another data set seed, or another sequence id, gives another street.
  const SimScan other_seed = SequenceSimulator(sequence_seed(kSeed + 1, kSequence), 1).scan(0);
  const SimScan other_id = SequenceSimulator(sequence_seed(kSeed, kSequence + 1), 1).scan(0);
  EXPECT_NE(other_seed.labels, w.scans[0].labels);
  EXPECT_NE(other_id.labels, w.scans[0].labels);
  EXPECT_NE(sequence_seed(kSeed, 0), sequence_seed(kSeed, 1));
}

TEST(SimSequence, PointsComeBeamByBeamOnTheBeamTable) {
  const Written& w = written();
  const auto& table = w.sim->lidar().elevation_deg;
  for (const Scan& s : w.scans) {
    int prev_beam = -1;
    double prev_az = -10;
    int64_t off_table = 0;
    for (const Point& p : s.points) {
      const double el = std::atan2(p.z, std::hypot(p.x, p.y)) * 180 / kPi;
      int beam = 0;
      for (int b = 1; b < 64; ++b)
        if (std::abs(table[static_cast<size_t>(b)] - el) <
            std::abs(table[static_cast<size_t>(beam)] - el))
          beam = b;
      off_table += std::abs(table[static_cast<size_t>(beam)] - el) > 0.005;
      const double az = std::atan2(p.y, p.x);
      ASSERT_GE(beam, prev_beam) << "beams come top to bottom";
      if (beam == prev_beam) {
        ASSERT_GT(az, prev_az) << "azimuth increases within a beam";
      }
      prev_beam = beam;
      prev_az = az;
    }
    // Outliers (raw 1) lie on their pulse too, so every return is on the table.
    EXPECT_EQ(off_table, 0);
  }
}

TEST(SimSequence, RoadNearTheCarLiesAboutMinus173) {
  const Written& w = written();
  std::vector<double> heights;
  for (const Scan& s : w.scans)
    for (size_t i = 0; i < s.points.size(); ++i) {
      const uint32_t sem = s.labels[i] & 0xFFFF;
      const Point& p = s.points[i];
      const double r = std::hypot(p.x, p.y);
      if ((sem == raw::kRoad || sem == raw::kLaneMarking) && r > 4 && r < 15) {
        heights.push_back(p.z);
        // The real labelled scan's road reaches 0.46 m below it (p5 -2.19, docs/simulator.md).
        EXPECT_NEAR(p.z, -kSensorHeight, 0.46) << "grades and camber, not cliffs";
      }
    }
  ASSERT_GT(heights.size(), 10000u);
  EXPECT_NEAR(median(heights), -kSensorHeight, 0.1);
  std::sort(heights.begin(), heights.end());
  EXPECT_GT(heights[heights.size() * 95 / 100] - heights[heights.size() * 5 / 100], 0.04)
      << "the road is not a plane at the sensor's feet";
}

TEST(SimSequence, ReflectanceOverlapsBetweenGroundsAndReadsZeroWhenWeak) {
  const Written& w = written();
  std::map<uint32_t, std::vector<double>> near;  // within 20 m, per raw id
  int64_t vehicle = 0, vehicle_zero = 0, far_road = 0, far_road_zero = 0, near_road_zero = 0;
  for (const Scan& s : w.scans)
    for (size_t i = 0; i < s.points.size(); ++i) {
      const uint32_t sem = s.labels[i] & 0xFFFF;
      const Point& p = s.points[i];
      const double r = std::hypot(p.x, p.y);
      if (r < 20) near[sem].push_back(p.r);
      if (sem == raw::kCar || sem == raw::kMovingCar) {
        ++vehicle;
        vehicle_zero += p.r == 0.f;
      }
      if (sem == raw::kRoad && r > 35) {
        ++far_road;
        far_road_zero += p.r == 0.f;
      }
      if (sem == raw::kRoad && r < 10) near_road_zero += p.r == 0.f;
    }
  ASSERT_GT(near[raw::kRoad].size(), 10000u);
  ASSERT_GT(near[raw::kSidewalk].size(), 1000u);
  ASSERT_GT(near[raw::kTerrain].size(), 1000u);
  // In KITTI the overlaps are 0.53, 0.44 and 0.77 (docs/simulator.md).
  EXPECT_GT(overlap(near[raw::kRoad], near[raw::kSidewalk]), 0.15);
  EXPECT_GT(overlap(near[raw::kRoad], near[raw::kTerrain]), 0.1);
  EXPECT_GT(overlap(near[raw::kSidewalk], near[raw::kTerrain]), 0.4);
  // Most cars read 0, as in KITTI; far road more often than near road.
  ASSERT_GT(vehicle, 2000);
  EXPECT_GT(vehicle_zero, vehicle / 2);
  ASSERT_GT(far_road, 200);
  EXPECT_GT(static_cast<double>(far_road_zero) / far_road,
            2.0 * static_cast<double>(near_road_zero) / near[raw::kRoad].size());
}

TEST(SimSequence, LowestBeamsDropAboutHalfTheirPulses) {
  const Written& w = written();
  const auto& table = w.sim->lidar().elevation_deg;
  std::array<int64_t, 64> returns{};
  for (const Scan& s : w.scans)
    for (const Point& p : s.points) {
      const double el = std::atan2(p.z, std::hypot(p.x, p.y)) * 180 / kPi;
      int beam = 0;
      for (int b = 1; b < 64; ++b)
        if (std::abs(table[static_cast<size_t>(b)] - el) <
            std::abs(table[static_cast<size_t>(beam)] - el))
          beam = b;
      ++returns[static_cast<size_t>(beam)];
    }
  // Beams between -20 and -12 deg see the ground all round but for the ego body.
  double low = 0, mid = 0;
  int n_low = 0, n_mid = 0;
  for (int b = 0; b < 64; ++b) {
    const double el = table[static_cast<size_t>(b)];
    if (el < -20) low += returns[static_cast<size_t>(b)], ++n_low;
    if (el > -20 && el < -12) mid += returns[static_cast<size_t>(b)], ++n_mid;
  }
  ASSERT_GT(n_low, 5);
  ASSERT_GT(n_mid, 5);
  const double ratio = (low / n_low) / (mid / n_mid);
  EXPECT_GT(ratio, 0.35);
  EXPECT_LT(ratio, 0.8);
}

TEST(SimSequence, EveryClassWithRareOnesInQuantity) {
  const Written& w = written();
  const ClassTable classes = ClassTable::defaults();
  std::array<int64_t, kNumClassIds> count{};
  std::map<uint32_t, double> reflectance_sum, reflectance_n;
  for (const Scan& s : w.scans)
    for (size_t i = 0; i < s.points.size(); ++i) {
      const uint32_t label = s.labels[i], sem = label & 0xFFFF, instance = label >> 16;
      const int c = classes.class_of(label);
      ++count[static_cast<size_t>(c)];
      // Things (vehicles, people, two-wheelers, riders) carry an instance id, stuff does not.
      if (c >= 1 && c <= 4) {
        EXPECT_NE(instance, 0u) << "raw " << sem;
      } else if (c >= 5) {
        EXPECT_EQ(instance, 0u) << "raw " << sem;
      }
      reflectance_sum[sem] += s.points[i].r;
      reflectance_n[sem] += 1;
    }
  for (int c = 1; c <= kNumClasses; ++c)
    EXPECT_GE(count[static_cast<size_t>(c)], 100) << classes.name(c);
  for (int c : {2, 3, 4})
    EXPECT_GE(count[static_cast<size_t>(c)] / kScans, 200) << classes.name(c) << " per scan";
  EXPECT_GT(count[0], 0) << "a few unlabeled / outlier points";
  const auto mean = [&](uint32_t sem) { return reflectance_sum[sem] / reflectance_n[sem]; };
  EXPECT_GT(mean(raw::kLaneMarking), mean(raw::kRoad) + 0.1) << "lane marks are bright";
  // Retroreflective signs, dimmer with the range like everything else (the real labelled
  // scan's: 0.41 within 15 m, 0.31 at 15-30 m).
  EXPECT_GT(mean(raw::kTrafficSign), 0.45) << "signs are retroreflective";
  EXPECT_GT(mean(raw::kTrafficSign), 1.5 * mean(raw::kPole)) << "signs are retroreflective";
}

TEST(SimSequence, MovingAgentsMoveAndTheirPointsFollowThem) {
  const Written& w = written();
  const City& city = w.sim->city();
  std::map<uint32_t, const MovingAgent*> movers;
  for (const MovingAgent& m : city.movers()) movers[m.agent.label >> 16] = &m;
  const auto inside = [&](const MovingAgent& m, double t, const Vector3d& q) {
    const Placement p = city.mover_pose(m, t);
    const double dx = q.x() - p.x, dy = q.y() - p.y;
    const double lx = std::cos(p.yaw) * dx + std::sin(p.yaw) * dy,
                 ly = -std::sin(p.yaw) * dx + std::cos(p.yaw) * dy;
    return std::abs(lx) <= 0.5 * m.agent.length + 0.3 &&
           std::abs(ly) <= 0.5 * m.agent.width + 0.35 && q.z() - p.z >= -0.1 &&
           q.z() - p.z <= m.agent.height + 0.3;
  };
  int64_t moving_points = 0, outside_now = 0, fast_points = 0, outside_later = 0;
  std::vector<double> shift_errors;
  for (int i = 0; i < kScans; ++i) {
    const Pose pose = w.sim->lidar_pose_world(i);
    const double t = SequenceSimulator::scan_time(i);
    const Scan& s = w.scans[static_cast<size_t>(i)];
    for (size_t k = 0; k < s.points.size(); ++k) {
      const uint32_t sem = s.labels[k] & 0xFFFF;
      if (sem < 252 || sem > 259) continue;
      const auto it = movers.find(s.labels[k] >> 16);
      ASSERT_NE(it, movers.end()) << "moving point of unknown instance " << (s.labels[k] >> 16);
      const Vector3d q = to_world(pose, s.points[k]);
      ++moving_points;
      outside_now += !inside(*it->second, t, q);
      if (it->second->speed > 3.0) {
        ++fast_points;
        outside_later += !inside(*it->second, t + 1.0, q);
      }
    }
  }
  ASSERT_GT(moving_points, 2000);
  EXPECT_EQ(outside_now, 0) << "every moving point lies on its agent posed at the scan time";
  ASSERT_GT(fast_points, 500);
  EXPECT_GT(outside_later, fast_points * 9 / 10) << "1 s later the agents have moved on";

  // From the files alone: centroids of moving instances in the world move between consecutive
  // scans by about what their agents travel in 0.1 s.
  for (int i = 0; i + 1 < kScans; ++i) {
    std::map<uint32_t, std::pair<Vector3d, int>> a, b;
    for (int j : {i, i + 1}) {
      auto& acc = j == i ? a : b;
      const Scan& s = w.scans[static_cast<size_t>(j)];
      for (size_t k = 0; k < s.points.size(); ++k) {
        const uint32_t sem = s.labels[k] & 0xFFFF;
        if (sem < 252 || sem > 259) continue;
        auto& [sum, n] = acc[s.labels[k] >> 16];
        if (n == 0) sum.setZero();
        sum += to_world(w.seq->pose(static_cast<size_t>(j)), s.points[k]);
        ++n;
      }
    }
    for (const auto& [id, an] : a) {
      const auto bt = b.find(id);
      if (an.second < 80 || bt == b.end() || bt->second.second < 80) continue;
      const double shift =
          (bt->second.first / bt->second.second - an.first / an.second).head<2>().norm();
      const Placement p0 = city.mover_pose(*movers[id], SequenceSimulator::scan_time(i));
      const Placement p1 = city.mover_pose(*movers[id], SequenceSimulator::scan_time(i + 1));
      const double travelled = std::hypot(p1.x - p0.x, p1.y - p0.y);
      EXPECT_GT(travelled, 0.08) << "instance " << id << " moves at least 0.8 m/s";
      shift_errors.push_back(std::abs(shift - travelled));
    }
  }
  ASSERT_GE(shift_errors.size(), 5u);
  EXPECT_LT(median(shift_errors), 0.1);
}

TEST(SimSequence, StaticPointsOfTwoScansCoincideThroughThePoses) {
  const Written& w = written();
  // Flat static surfaces: facades and fences.
  const auto building_points = [&](size_t i, const Pose& to_frame) {
    std::vector<Vector3d> out;
    const Scan& s = w.scans[i];
    for (size_t k = 0; k < s.points.size(); ++k) {
      const Point& p = s.points[k];
      const uint32_t sem = s.labels[k] & 0xFFFF;
      if ((sem == raw::kBuilding || sem == raw::kFence) && std::hypot(p.x, p.y) < 40)
        out.push_back(to_world(to_frame, p));
    }
    return out;
  };
  const std::vector<Vector3d> first = building_points(0, Pose::Identity());
  ASSERT_GT(first.size(), 2000u);
  const Pose relative = w.seq->relative(0, kScans - 1);
  ASSERT_GT((relative.topRightCorner<3, 1>().norm()), 2.0) << "the ego moved";
  // Facade points of the last scan, brought into the first scan's frame, lie on the facades
  // the first scan saw (up to the 2 cm range noise of both); 0.3 m off, they do not.
  const std::vector<double> aligned = plane_distances(first, building_points(kScans - 1, relative));
  Pose shifted = relative;
  shifted(1, 3) += 0.3;
  shifted(0, 3) += 0.3;
  const std::vector<double> misaligned =
      plane_distances(first, building_points(kScans - 1, shifted));
  ASSERT_GT(aligned.size(), 1000u);
  EXPECT_LT(median(aligned), 0.025);
  EXPECT_GT(median(misaligned), 0.15);
}

TEST(SimSequence, PosesAndCalibMatchTheTrueLidarMotion) {
  const Written& w = written();
  const Calib calib = read_calib(w.seq->dir() / "calib.txt");
  Eigen::Matrix3d swap;
  swap << 0, -1, 0, 0, 0, -1, 1, 0, 0;
  const Eigen::Matrix3d tilt = calib.Tr.topLeftCorner<3, 3>() * swap.transpose();
  EXPECT_LT(Eigen::AngleAxisd(tilt).angle(), 2.0 * kPi / 180)
      << "Tr is KITTI's axis swap, slightly tilted";
  EXPECT_NEAR(calib.Tr(1, 3), -0.08, 0.05);
  EXPECT_NEAR(calib.Tr(2, 3), -0.27, 0.05);
  const Pose first_inv = w.sim->lidar_pose_world(0).inverse();
  for (int i = 0; i < kScans; ++i) {
    const Pose expected = first_inv * w.sim->lidar_pose_world(i);
    const Pose& actual = w.seq->pose(static_cast<size_t>(i));
    EXPECT_TRUE(test::all_close(actual.data(), expected.data(), 16, 1e-8, 1e-8)) << "scan " << i;
  }
  const auto cam0 = read_poses(w.seq->dir() / "poses.txt");
  ASSERT_EQ(cam0.size(), static_cast<size_t>(kScans));
  EXPECT_TRUE(cam0[0].isApprox(Pose::Identity(), 1e-9))
      << "poses are relative to the first cam0 frame";
  // The camera looks forward: cam0 moves along its z axis.
  EXPECT_GT(cam0.back()(2, 3), 2.0);
}

TEST(SimSequence, RejectsOptionsItCannotWrite) {
  SimulateOptions options;
  options.out = test::temp_dir();
  options.sequences = 0;
  EXPECT_THROW(simulate(options), Error);
  options.sequences = 2;
  options.first_sequence = 99;
  try {
    simulate(options);
    ADD_FAILURE() << "sequence id 100 accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("two digits"), std::string::npos) << e.what();
  }
  options.first_sequence = 0;
  options.scans = 0;
  EXPECT_THROW(simulate(options), Error);
  EXPECT_FALSE(fs::exists(options.out / "sequences")) << "nothing written for bad options";
}
