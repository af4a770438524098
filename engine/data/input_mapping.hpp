// InputMapping: a sensor's points into the frame and scale the model was trained in (DESIGN.md
// section 11): the sensor at the origin, x forward, z up, reflectance in [0, 1]. It comes from a
// run config's `input:` section, infer's options or the C API's options (docs/formats.md), and is
// applied to the points before anything else sees them: by the segmenter at inference, and by a
// data set's Sequence (its scans and poses) in training and evaluation.
#pragma once

#include <span>
#include <string>

#include "core/hash.hpp"
#include "core/point.hpp"

namespace YAML {
class Node;
}

namespace pillarseg {

struct ReflectanceMapping {
  enum class Kind {
    Keep,   // as stored
    Scale,  // scale * r + offset, clamped to [0, 1] with clip
    None,   // the sensor gives none: every point gets 0
  };
  Kind kind = Kind::Keep;
  float scale = 1, offset = 0;
  bool clip = true;
};

struct InputMapping {
  ReflectanceMapping reflectance;
  // Affine, row-major, bottom row 0 0 0 1: p_model = transform * p_sensor.
  Pose transform = Pose::Identity();

  bool is_identity() const;
  // Maps the points in place (x, y, z by the transform, in double, rounded to float once; then r).
  void apply(std::span<Point> points) const;
  // Adds what changes the mapped points to a cache key: nothing for the identity, so that keys of
  // unmapped data are unchanged.
  void add_to(Hasher& hasher) const;
  // One line for logs: "reflectance x 0.00392 + 0 clipped, transform [...]" or "identity".
  std::string describe() const;
};

// The transform of a sensor rolled, pitched and yawed (degrees) and with `height` metres added to
// z: p_model = Rz(yaw) Ry(pitch) Rx(roll) p_sensor + (0, 0, height).
Pose transform_from_angles(double height, double roll_degrees, double pitch_degrees, double yaw_degrees);
// A transform of 16 row-major numbers; `where` names the source in errors.
Pose transform_from_numbers(std::span<const double> numbers, const std::string& where);
// Checks that a transform is finite, affine (bottom row 0 0 0 1) and invertible.
void check_transform(const Pose& transform, const std::string& where);

// The `input:` section of a run config: {reflectance: {scale, offset, clip} | none,
// transform: 4 x 4 (rows, or 16 numbers) | {height, roll, pitch, yaw}}; unknown keys are errors,
// `where` prefixes them ("configs/x.yaml: input").
InputMapping parse_input_mapping(const YAML::Node& section, const std::string& where);

}  // namespace pillarseg
