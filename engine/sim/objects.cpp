#include "engine/sim/objects.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

namespace pillarseg::sim {

namespace {

using Eigen::Vector3d;

// Adds parts given in the object's local frame to `out`, posed by a Placement.
class Builder {
 public:
  Builder(const Placement& at, std::vector<Primitive>& out)
      : at_(at), c_(std::cos(at.yaw)), s_(std::sin(at.yaw)), out_(out) {}

  Vector3d world(double x, double y, double z) const {
    return {at_.x + c_ * x - s_ * y, at_.y + s_ * x + c_ * y, at_.z + z};
  }
  // Box centred at local (x, y, z) with half sizes (hx, hy, hz), turned by yaw about its centre.
  void box(double x, double y, double z, double hx, double hy, double hz, uint32_t label,
           float albedo, Surface surface = Surface::kSolid, double yaw = 0.0) {
    out_.push_back(make_box(world(x, y, z), {hx, hy, hz}, at_.yaw + yaw, label, albedo, surface));
  }
  void cylinder(double x, double y, double z0, double z1, double radius, uint32_t label,
                float albedo) {
    const Vector3d p = world(x, y, 0);
    out_.push_back(make_cylinder(p.x(), p.y(), at_.z + z0, at_.z + z1, radius, label, albedo));
  }
  void ellipsoid(double x, double y, double z, double rx, double ry, double rz, uint32_t label,
                 float albedo, Surface surface = Surface::kSolid) {
    out_.push_back(make_ellipsoid(world(x, y, z), {rx, ry, rz}, at_.yaw, label, albedo, surface));
  }

 private:
  Placement at_;
  double c_, s_;
  std::vector<Primitive>& out_;
};

constexpr float kTyreAlbedo = 0.05f;

float paint_albedo(Rng& rng) {
  // Dark, mid and bright paints, as in KITTI where most cars return so little light that the
  // sensor reads 0 (80% of the vehicle points of the real labelled scan).
  const double u = rng.uniform();
  if (u < 0.75) return static_cast<float>(rng.uniform(0.0, 0.05));
  if (u < 0.9) return static_cast<float>(rng.uniform(0.05, 0.30));
  return static_cast<float>(rng.uniform(0.30, 0.60));
}

void emit_car(const Agent& a, Builder& b) {
  const double l = a.length, w = a.width, h = a.height;
  const double body_top = 0.28 + 0.45 * h;
  b.box(0, 0, 0.5 * (0.28 + body_top), 0.5 * l, 0.5 * w, 0.5 * (body_top - 0.28), a.label,
        a.albedo);
  b.box(-0.06 * l, 0, 0.5 * (body_top + h), 0.27 * l, 0.5 * w - 0.07, 0.5 * (h - body_top), a.label,
        a.albedo, Surface::kGlass);
  for (int sx : {-1, 1})
    for (int sy : {-1, 1})
      b.box(sx * (0.5 * l - 0.85), sy * (0.5 * w - 0.12), 0.31, 0.31, 0.1, 0.31, a.label,
            kTyreAlbedo);
}

void emit_truck(const Agent& a, Builder& b) {
  const double l = a.length, w = a.width, h = a.height;
  const double cab = 2.3;
  b.box(0.5 * l - 0.5 * cab, 0, 0.5 * (0.5 + 2.9), 0.5 * cab, 0.5 * w, 0.5 * (2.9 - 0.5), a.label,
        a.albedo);
  const double cargo = l - cab - 0.15;
  b.box(-0.5 * l + 0.5 * cargo, 0, 0.5 * (0.95 + h), 0.5 * cargo, 0.5 * w, 0.5 * (h - 0.95),
        a.label, a.albedo * 0.8f + 0.1f);
  b.box(-0.5 * l + 0.5 * cargo, 0, 0.72, 0.5 * cargo, 0.5 * w - 0.35, 0.23, a.label, 0.1f);
  for (double x : {0.5 * l - 1.3, -0.5 * l + 1.1, -0.5 * l + 2.2})
    for (int sy : {-1, 1})
      b.box(x, sy * (0.5 * w - 0.2), 0.5, 0.5, 0.15, 0.5, a.label, kTyreAlbedo);
}

void emit_bus(const Agent& a, Builder& b) {
  const double l = a.length, w = a.width, h = a.height;
  b.box(0, 0, 0.5 * (0.35 + 1.1), 0.5 * l, 0.5 * w, 0.5 * (1.1 - 0.35), a.label, a.albedo);
  b.box(0, 0, 0.5 * (1.1 + h - 0.3), 0.5 * l - 0.05, 0.5 * w - 0.03, 0.5 * (h - 0.3 - 1.1), a.label,
        a.albedo, Surface::kGlass);
  b.box(0, 0, h - 0.15, 0.5 * l, 0.5 * w, 0.15, a.label, a.albedo);
  for (double x : {0.5 * l - 2.5, -0.5 * l + 3.0})
    for (int sy : {-1, 1})
      b.box(x, sy * (0.5 * w - 0.2), 0.5, 0.5, 0.15, 0.5, a.label, kTyreAlbedo);
}

void emit_trailer(const Agent& a, Builder& b) {
  const double l = a.length, w = a.width, h = a.height;
  b.box(0, 0, 0.5 * (0.45 + h), 0.5 * l, 0.5 * w, 0.5 * (h - 0.45), a.label, a.albedo);
  b.box(0.5 * l + 0.6, 0, 0.45, 0.6, 0.08, 0.06, a.label, 0.15f);
  for (int sy : {-1, 1}) b.box(0, sy * (0.5 * w - 0.15), 0.3, 0.3, 0.1, 0.3, a.label, kTyreAlbedo);
}

void emit_person(const Agent& a, double phase, Builder& b) {
  const double h = a.height, s = h / 1.75;
  const double stride = 0.2 * s * std::sin(phase);
  const double hip = 0.48 * h, shoulder = 0.81 * h;
  for (int side : {-1, 1}) {
    b.cylinder(side * stride, side * 0.1 * s, 0.0, hip, 0.075 * s, a.label, a.albedo * 0.8f);
    b.box(-side * 0.6 * stride, side * 0.25 * s, 0.5 * (hip + shoulder) + 0.02 * h, 0.05 * s,
          0.045 * s, 0.15 * h, a.label, a.albedo);
  }
  b.box(0, 0, 0.5 * (hip + shoulder), 0.11 * s, 0.19 * s, 0.5 * (shoulder - hip), a.label,
        a.albedo);
  b.ellipsoid(0, 0, h - 0.115 * s, 0.1 * s, 0.085 * s, 0.115 * s, a.label, 0.35f);
}

void emit_bicycle(uint32_t label, float albedo, Builder& b) {
  for (int sx : {-1, 1}) b.box(sx * 0.52, 0, 0.34, 0.34, 0.02, 0.34, label, albedo, Surface::kMesh);
  b.box(0, 0, 0.58, 0.4, 0.025, 0.1, label, albedo);
  b.box(-0.22, 0, 0.73, 0.02, 0.02, 0.17, label, albedo);
  b.box(-0.25, 0, 0.92, 0.12, 0.07, 0.03, label, 0.1f);
  b.box(0.43, 0, 0.8, 0.025, 0.025, 0.2, label, albedo);
  b.box(0.45, 0, 1.0, 0.03, 0.3, 0.03, label, albedo);
}

void emit_motorcycle(uint32_t label, float albedo, Builder& b) {
  for (int sx : {-1, 1}) b.box(sx * 0.7, 0, 0.31, 0.31, 0.06, 0.31, label, kTyreAlbedo);
  b.box(0, 0, 0.6, 0.5, 0.2, 0.2, label, albedo);
  b.box(-0.1, 0, 0.88, 0.5, 0.17, 0.09, label, albedo);
  b.box(0.62, 0, 0.8, 0.12, 0.22, 0.2, label, albedo);
  b.box(0.5, 0, 1.05, 0.05, 0.36, 0.04, label, 0.15f);
}

// The rider on a bicycle (seat ~0.95 m) or a motorcycle (seat ~0.9 m, wider posture).
void emit_rider(const Agent& a, bool motorcycle, Builder& b) {
  const double s = a.height / 1.75;
  const uint32_t l = a.label;
  if (motorcycle) {
    for (int side : {-1, 1}) {
      b.box(0.05, side * 0.2, 0.82, 0.25, 0.08, 0.1, l, a.albedo);
      b.box(0.3, side * 0.24, 1.15, 0.22, 0.05, 0.05, l, a.albedo);
    }
    b.box(-0.1, 0, 0.95 + 0.26 * s, 0.15 * s, 0.2 * s, 0.26 * s, l, a.albedo);
    b.ellipsoid(0.0, 0, 0.95 + 0.52 * s + 0.14, 0.14, 0.13, 0.15, l, 0.5f);
  } else {
    for (int side : {-1, 1}) {
      b.box(-0.08, side * 0.14, 0.7, 0.1 * s, 0.065 * s, 0.24 * s, l, a.albedo * 0.8f);
      b.box(0.25, side * 0.22, 1.15, 0.2, 0.045, 0.045, l, a.albedo);
    }
    b.box(0.0, 0, 0.95 + 0.27 * s, 0.14 * s, 0.19 * s, 0.24 * s, l, a.albedo);
    b.ellipsoid(0.1, 0, 0.95 + 0.51 * s + 0.115 * s, 0.1 * s, 0.085 * s, 0.115 * s, l, 0.35f);
  }
}

}  // namespace

Agent sample_agent(AgentKind kind, uint32_t label, uint32_t vehicle_label, Rng& rng) {
  Agent a;
  a.kind = kind;
  a.label = label;
  a.vehicle_label = vehicle_label;
  switch (kind) {
    case AgentKind::kCar:
      if (rng.bernoulli(0.15)) {  // vans and SUVs
        a.length = rng.uniform(4.7, 5.3), a.width = rng.uniform(1.9, 2.05),
        a.height = rng.uniform(1.75, 2.05);
      } else {
        a.length = rng.uniform(3.8, 4.9), a.width = rng.uniform(1.7, 1.9),
        a.height = rng.uniform(1.4, 1.6);
      }
      a.albedo = paint_albedo(rng);
      break;
    case AgentKind::kTruck:
      a.length = rng.uniform(6.5, 9.5), a.width = 2.45, a.height = rng.uniform(3.0, 3.8);
      a.albedo = static_cast<float>(rng.uniform(0.2, 0.55));
      break;
    case AgentKind::kBus:
      a.length = rng.uniform(10.0, 12.5), a.width = 2.55, a.height = rng.uniform(2.9, 3.2);
      a.albedo = static_cast<float>(rng.uniform(0.25, 0.6));
      break;
    case AgentKind::kTrailer:
      a.length = rng.uniform(4.5, 6.5), a.width = rng.uniform(2.1, 2.35),
      a.height = rng.uniform(2.3, 2.8);
      a.albedo = static_cast<float>(rng.uniform(0.3, 0.65));
      break;
    case AgentKind::kPerson:
      a.height = rng.uniform(1.55, 1.92), a.length = 0.35, a.width = 0.55;
      a.albedo = static_cast<float>(rng.uniform(0.08, 0.45));
      break;
    case AgentKind::kBicycle:
    case AgentKind::kBicyclist:
      a.length = 1.75, a.width = 0.6,
      a.height = kind == AgentKind::kBicycle ? 1.05 : rng.uniform(1.6, 1.85);
      a.albedo = static_cast<float>(rng.uniform(0.12, 0.4));
      break;
    case AgentKind::kMotorcycle:
    case AgentKind::kMotorcyclist:
      a.length = 2.1, a.width = 0.8,
      a.height = kind == AgentKind::kMotorcycle ? 1.15 : rng.uniform(1.6, 1.8);
      a.albedo = static_cast<float>(rng.uniform(0.1, 0.5));
      break;
  }
  return a;
}

void emit_agent(const Agent& agent, const Placement& at, double phase,
                std::vector<Primitive>& out) {
  Builder b(at, out);
  switch (agent.kind) {
    case AgentKind::kCar:
      emit_car(agent, b);
      break;
    case AgentKind::kTruck:
      emit_truck(agent, b);
      break;
    case AgentKind::kBus:
      emit_bus(agent, b);
      break;
    case AgentKind::kTrailer:
      emit_trailer(agent, b);
      break;
    case AgentKind::kPerson:
      emit_person(agent, phase, b);
      break;
    case AgentKind::kBicycle:
      emit_bicycle(agent.label, agent.albedo, b);
      break;
    case AgentKind::kMotorcycle:
      emit_motorcycle(agent.label, agent.albedo, b);
      break;
    case AgentKind::kBicyclist:
      emit_bicycle(agent.vehicle_label, 0.25f, b);
      emit_rider(agent, false, b);
      break;
    case AgentKind::kMotorcyclist:
      emit_motorcycle(agent.vehicle_label, 0.3f, b);
      emit_rider(agent, true, b);
      break;
  }
}

TreeShape sample_tree(Rng& rng) {
  TreeShape t;
  t.trunk_radius = rng.uniform(0.12, 0.3);
  t.crown_base = rng.uniform(1.3, 2.6);
  t.crown_radius = rng.uniform(1.5, 3.5);
  t.crown_half_height = rng.uniform(1.5, 3.0);
  t.trunk_albedo = static_cast<float>(rng.uniform(0.3, 0.5));
  t.crown_albedo = static_cast<float>(rng.uniform(0.3, 0.5));
  const int lobes = 2 + static_cast<int>(rng.uniform_int(3));
  for (int i = 0; i < lobes; ++i) {
    const double angle = rng.uniform(-std::numbers::pi, std::numbers::pi);
    const double reach = rng.uniform(0.4, 0.8) * t.crown_radius;
    const double dz = rng.uniform(-0.5, 0.6) * t.crown_half_height;
    const double radius = rng.uniform(0.35, 0.6) * t.crown_radius;
    t.lobes.emplace_back(reach * std::cos(angle), reach * std::sin(angle), dz, radius);
  }
  return t;
}

void emit_tree(const TreeShape& tree, const Placement& at, uint32_t trunk_label,
               uint32_t crown_label, std::vector<Primitive>& out) {
  Builder b(at, out);
  // The trunk reaches into the crown, so that pulses through the foliage still find it.
  const double top = tree.crown_base + 1.2 * tree.crown_half_height;
  b.cylinder(0, 0, 0, top, tree.trunk_radius, trunk_label, tree.trunk_albedo);
  const double mid = tree.crown_base + tree.crown_half_height;
  b.ellipsoid(0, 0, mid, 0.85 * tree.crown_radius, 0.8 * tree.crown_radius, tree.crown_half_height,
              crown_label, tree.crown_albedo, Surface::kFoliage);
  for (const Eigen::Vector4d& lobe : tree.lobes)
    b.ellipsoid(lobe.x(), lobe.y(), std::max(mid + lobe.z(), tree.crown_base + 0.5 * lobe.w()),
                lobe.w(), lobe.w(), 0.8 * lobe.w(), crown_label, tree.crown_albedo,
                Surface::kFoliage);
}

void emit_street_lamp(const Placement& at, double height, uint32_t pole_label,
                      std::vector<Primitive>& out) {
  Builder b(at, out);
  b.cylinder(0, 0, 0, height, 0.1, pole_label, 0.3f);
  b.box(0.8, 0, height - 0.1, 0.8, 0.04, 0.04, pole_label, 0.3f);
  b.box(1.5, 0, height - 0.25, 0.3, 0.15, 0.08, pole_label, 0.45f);
}

void emit_traffic_sign(const Placement& at, double height, int plates, uint32_t pole_label,
                       uint32_t sign_label, std::vector<Primitive>& out) {
  Builder b(at, out);
  b.cylinder(0, 0, 0, height, 0.045, pole_label, 0.3f);
  for (int i = 0; i < plates; ++i)
    b.box(0.06, 0, height - 0.3 - 0.65 * i, 0.02, 0.32, 0.3, sign_label, 0.9f);
}

}  // namespace pillarseg::sim
