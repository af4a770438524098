// Objects of the simulated street, built from scene primitives: traffic participants (cars,
// trucks, buses, trailers, people, bicycles, motorcycles and their riders) with sizes that
// tell them apart in a top view with height, and street furniture (trees, lamps, signs).
// An object is built in its local frame (x forward, y left, z up from its base on the ground)
// and posed by a Placement.
#pragma once

#include <cstdint>
#include <vector>

#include "core/rng.hpp"
#include "engine/sim/scene.hpp"

namespace pillarseg::sim {

// Raw SemanticKITTI semantic ids the simulator writes.
namespace raw {
inline constexpr uint32_t kUnlabeled = 0, kOutlier = 1;
inline constexpr uint32_t kCar = 10, kBicycle = 11, kMotorcycle = 15, kTruck = 18,
                          kOtherVehicle = 20;
inline constexpr uint32_t kPerson = 30, kBicyclist = 31, kMotorcyclist = 32;
inline constexpr uint32_t kRoad = 40, kParking = 44, kSidewalk = 48, kOtherGround = 49;
inline constexpr uint32_t kBuilding = 50, kFence = 51, kOtherStructure = 52, kLaneMarking = 60;
inline constexpr uint32_t kVegetation = 70, kTrunk = 71, kTerrain = 72, kPole = 80,
                          kTrafficSign = 81;
inline constexpr uint32_t kOtherObject = 99;
inline constexpr uint32_t kMovingCar = 252, kMovingBicyclist = 253, kMovingPerson = 254;
inline constexpr uint32_t kMovingMotorcyclist = 255, kMovingTruck = 258, kMovingOtherVehicle = 259;
}  // namespace raw

// The raw .label word of an object part.
inline uint32_t label_word(uint32_t semantic, uint32_t instance) {
  return (instance << 16) | semantic;
}

enum class AgentKind : uint8_t {
  kCar,
  kTruck,
  kBus,
  kTrailer,
  kPerson,
  kBicycle,
  kMotorcycle,
  kBicyclist,    // a person riding a bicycle
  kMotorcyclist  // a person riding a motorcycle
};

struct Agent {
  AgentKind kind = AgentKind::kCar;
  double length = 4.5, width = 1.8, height = 1.5;  // overall size in metres
  float albedo = 0.2f;                             // paint or clothes
  uint32_t label = 0;          // raw word of the body: the vehicle, the person, or the rider
  uint32_t vehicle_label = 0;  // raw word of a rider's bicycle or motorcycle
};

// Base centre on the ground and heading (radians, of the local +x axis) of an object.
struct Placement {
  double x = 0, y = 0, z = 0, yaw = 0;
};

// An agent of the kind with sizes and albedo drawn from rng. A rider's two-wheeler gets
// vehicle_label (a moving rider and his bicycle share one label; a standing one does not).
Agent sample_agent(AgentKind kind, uint32_t label, uint32_t vehicle_label, Rng& rng);

// Appends the agent's primitives posed at `at`. phase (radians) is the gait phase of a walking
// person (legs and arms swing with sin(phase)); 0 for a standing one.
void emit_agent(const Agent& agent, const Placement& at, double phase, std::vector<Primitive>& out);

// A tree: a trunk (label trunk_label) up into a crown of foliage (crown_label): an ellipsoid
// with lobes of smaller ellipsoids around it, so that crowns are irregular.
struct TreeShape {
  double trunk_radius = 0.2, crown_base = 2.5;  // crown starts at this height above the base
  double crown_radius = 2.5, crown_half_height = 2.0;
  float trunk_albedo = 0.3f, crown_albedo = 0.4f;
  // Lobes: centre offset from the crown's centre (x, y, z) and radius, in metres.
  std::vector<Eigen::Vector4d> lobes;
};
TreeShape sample_tree(Rng& rng);
void emit_tree(const TreeShape& tree, const Placement& at, uint32_t trunk_label,
               uint32_t crown_label, std::vector<Primitive>& out);

// A street lamp facing +x of `at` (the road): pole, arm over the road, lamp head; all pole_label.
void emit_street_lamp(const Placement& at, double height, uint32_t pole_label,
                      std::vector<Primitive>& out);
// A traffic sign: a thin pole (pole_label) and one or two plates (sign_label) facing +x of `at`.
void emit_traffic_sign(const Placement& at, double height, int plates, uint32_t pole_label,
                       uint32_t sign_label, std::vector<Primitive>& out);

}  // namespace pillarseg::sim
