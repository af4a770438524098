#include "engine/data/input_mapping.hpp"

#include <fmt/format.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <vector>

#include "core/error.hpp"

namespace pillarseg {

bool InputMapping::is_identity() const {
  return reflectance.kind == ReflectanceMapping::Kind::Keep && transform == Pose::Identity();
}

void InputMapping::apply(std::span<Point> points) const {
  if (transform != Pose::Identity()) {
    const Eigen::Matrix3d rotation = transform.topLeftCorner<3, 3>();
    const Eigen::Vector3d translation = transform.topRightCorner<3, 1>();
    for (Point& p : points) {
      const Eigen::Vector3d q = rotation * Eigen::Vector3d(p.x, p.y, p.z) + translation;
      p.x = static_cast<float>(q.x()), p.y = static_cast<float>(q.y()), p.z = static_cast<float>(q.z());
    }
  }
  switch (reflectance.kind) {
    case ReflectanceMapping::Kind::Keep:
      break;
    case ReflectanceMapping::Kind::None:
      for (Point& p : points) p.r = 0.0f;
      break;
    case ReflectanceMapping::Kind::Scale:
      for (Point& p : points) {
        const float r = reflectance.scale * p.r + reflectance.offset;
        // A NaN stays NaN (the pipeline ignores the point), as the comparisons are false.
        p.r = reflectance.clip ? (r < 0.0f ? 0.0f : r > 1.0f ? 1.0f : r) : r;
      }
      break;
  }
}

void InputMapping::add_to(Hasher& hasher) const {
  if (is_identity()) return;
  hasher.add(std::string_view("input-mapping-1"));
  hasher.add(static_cast<int>(reflectance.kind));
  hasher.add(reflectance.scale);
  hasher.add(reflectance.offset);
  hasher.add(static_cast<int>(reflectance.clip));
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) hasher.add(transform(r, c));
}

std::string InputMapping::describe() const {
  if (is_identity()) return "identity";
  std::string text;
  switch (reflectance.kind) {
    case ReflectanceMapping::Kind::Keep: text = "reflectance as stored"; break;
    case ReflectanceMapping::Kind::None: text = "reflectance none (0)"; break;
    case ReflectanceMapping::Kind::Scale:
      text = fmt::format("reflectance x {:g} + {:g}{}", reflectance.scale, reflectance.offset,
                         reflectance.clip ? " clipped to [0, 1]" : "");
      break;
  }
  if (transform != Pose::Identity()) {
    std::vector<double> values;  // cos(90 degrees) and the like as 0
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) values.push_back(std::abs(transform(r, c)) < 1e-12 ? 0.0 : transform(r, c));
    text += fmt::format(", transform rows [{:.6g}]", fmt::join(values, " "));
  }
  return text;
}

Pose transform_from_angles(double height, double roll_degrees, double pitch_degrees, double yaw_degrees) {
  const double to_radians = std::numbers::pi / 180.0;
  Pose t = Pose::Identity();
  t.topLeftCorner<3, 3>() = (Eigen::AngleAxisd(yaw_degrees * to_radians, Eigen::Vector3d::UnitZ()) *
                             Eigen::AngleAxisd(pitch_degrees * to_radians, Eigen::Vector3d::UnitY()) *
                             Eigen::AngleAxisd(roll_degrees * to_radians, Eigen::Vector3d::UnitX()))
                                .toRotationMatrix();
  t(2, 3) = height;
  return t;
}

Pose transform_from_numbers(std::span<const double> numbers, const std::string& where) {
  PS_CHECK(numbers.size() == 16, "{}: {} numbers, expected 16 (a row-major 4 x 4 matrix)", where, numbers.size());
  Pose t;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) t(r, c) = numbers[static_cast<size_t>(r * 4 + c)];
  check_transform(t, where);
  return t;
}

void check_transform(const Pose& transform, const std::string& where) {
  PS_CHECK(transform.allFinite(), "{}: the transform has a value that is not finite", where);
  PS_CHECK(transform(3, 0) == 0 && transform(3, 1) == 0 && transform(3, 2) == 0 && transform(3, 3) == 1,
           "{}: the transform's bottom row is [{} {} {} {}], expected [0 0 0 1] (an affine map)", where,
           transform(3, 0), transform(3, 1), transform(3, 2), transform(3, 3));
  PS_CHECK(std::abs(transform.topLeftCorner<3, 3>().determinant()) > 1e-9,
           "{}: the transform's 3 x 3 part is singular (it would collapse the points)", where);
}

namespace {

double number(const YAML::Node& node, const std::string& where) {
  double v = 0;
  try {
    v = node.as<double>();
  } catch (const YAML::Exception&) {
    PS_FAIL("{}: expected a number", where);
  }
  PS_CHECK(std::isfinite(v), "{}: expected a finite number, got {}", where, v);
  return v;
}

ReflectanceMapping parse_reflectance(const YAML::Node& node, const std::string& where) {
  ReflectanceMapping m;
  if (node.IsScalar()) {
    PS_CHECK(node.Scalar() == "none", "{}: '{}': expected none or {{scale, offset, clip}}", where, node.Scalar());
    m.kind = ReflectanceMapping::Kind::None;
    return m;
  }
  PS_CHECK(node.IsMap(), "{}: expected none or {{scale, offset, clip}}", where);
  m.kind = ReflectanceMapping::Kind::Scale;
  for (const auto& kv : node) {
    const std::string key = kv.first.as<std::string>();
    const std::string w = where + "." + key;
    if (key == "scale") m.scale = static_cast<float>(number(kv.second, w));
    else if (key == "offset") m.offset = static_cast<float>(number(kv.second, w));
    else if (key == "clip") {
      try {
        m.clip = kv.second.as<bool>();
      } catch (const YAML::Exception&) {
        PS_FAIL("{}: expected true or false", w);
      }
    } else PS_FAIL("{}: unknown key (expected scale, offset, clip)", w);
  }
  return m;
}

Pose parse_transform(const YAML::Node& node, const std::string& where) {
  if (node.IsMap()) {
    double height = 0, roll = 0, pitch = 0, yaw = 0;
    for (const auto& kv : node) {
      const std::string key = kv.first.as<std::string>();
      const std::string w = where + "." + key;
      if (key == "height") height = number(kv.second, w);
      else if (key == "roll") roll = number(kv.second, w + " (degrees)");
      else if (key == "pitch") pitch = number(kv.second, w + " (degrees)");
      else if (key == "yaw") yaw = number(kv.second, w + " (degrees)");
      else PS_FAIL("{}: unknown key (expected height in metres, roll, pitch, yaw in degrees)", w);
    }
    return transform_from_angles(height, roll, pitch, yaw);
  }
  PS_CHECK(node.IsSequence(), "{}: expected a 4 x 4 matrix (4 rows of 4 numbers, or 16 numbers) or "
                              "{{height, roll, pitch, yaw}}", where);
  std::vector<double> numbers;
  const bool rows = node.size() == 4 && std::all_of(node.begin(), node.end(), [](const YAML::Node& r) {
                      return r.IsSequence();
                    });
  if (rows) {
    for (size_t r = 0; r < 4; ++r) {
      PS_CHECK(node[r].size() == 4, "{}: row {} has {} numbers, expected 4", where, r + 1, node[r].size());
      for (size_t c = 0; c < 4; ++c) numbers.push_back(number(node[r][c], fmt::format("{}[{}][{}]", where, r, c)));
    }
  } else {
    for (size_t i = 0; i < node.size(); ++i) numbers.push_back(number(node[i], fmt::format("{}[{}]", where, i)));
  }
  return transform_from_numbers(numbers, where);
}

}  // namespace

InputMapping parse_input_mapping(const YAML::Node& section, const std::string& where) {
  PS_CHECK(section.IsMap(), "{}: expected a mapping with reflectance and/or transform", where);
  InputMapping m;
  for (const auto& kv : section) {
    const std::string key = kv.first.as<std::string>();
    if (key == "reflectance") m.reflectance = parse_reflectance(kv.second, where + ".reflectance");
    else if (key == "transform") m.transform = parse_transform(kv.second, where + ".transform");
    else PS_FAIL("{}.{}: unknown key (expected reflectance, transform)", where, key);
  }
  return m;
}

}  // namespace pillarseg
