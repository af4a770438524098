#include "engine/data/semantickitti.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstring>
#include <ostream>
#include <sstream>

#include "core/eigen.hpp"
#include "core/error.hpp"
#include "core/io.hpp"
#include "core/memory_budget.hpp"
#include "engine/data/point_formats.hpp"

namespace pillarseg {

namespace fs = std::filesystem;

namespace {

// Parses whitespace-separated numbers of one line into out; returns false on a bad token.
bool parse_numbers(std::string_view text, std::vector<double>& out) {
  out.clear();
  size_t i = 0;
  while (i < text.size()) {
    while (i < text.size() && std::isspace(static_cast<unsigned char>(text[i]))) ++i;
    if (i == text.size()) break;
    size_t j = i;
    while (j < text.size() && !std::isspace(static_cast<unsigned char>(text[j]))) ++j;
    double v = 0;
    const auto [ptr, ec] = std::from_chars(text.data() + i, text.data() + j, v);
    if (ec != std::errc() || ptr != text.data() + j || !std::isfinite(v)) return false;
    out.push_back(v);
    i = j;
  }
  return true;
}

Pose pose_from_12(const std::vector<double>& v) {
  Pose p = Pose::Identity();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) p(r, c) = v[static_cast<size_t>(r * 4 + c)];
  return p;
}

void write_12(std::ostream& out, const Eigen::Matrix<double, 3, 4>& m) {
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) out << (r || c ? " " : "") << fmt::format("{:.12e}", m(r, c));
}

std::vector<std::string_view> split_lines(const std::string& text) {
  std::vector<std::string_view> lines;
  size_t start = 0;
  while (start <= text.size()) {
    size_t end = text.find('\n', start);
    if (end == std::string::npos) end = text.size();
    std::string_view line(text.data() + start, end - start);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    lines.push_back(line);
    if (end == text.size()) break;
    start = end + 1;
  }
  return lines;
}

bool blank(std::string_view s) {
  return std::all_of(s.begin(), s.end(), [](unsigned char c) { return std::isspace(c); });
}

}  // namespace

std::vector<uint32_t> read_labels(const fs::path& label_path) {
  // The file's bytes and the labels.
  require_records(label_path, sizeof(uint32_t), 2 * sizeof(uint32_t), "labels");
  const std::vector<char> bytes = read_file_bytes(label_path);
  PS_CHECK(bytes.size() % 4 == 0, "{}: size {} bytes is not a multiple of 4 (uint32 labels)", label_path.string(),
           bytes.size());
  std::vector<uint32_t> labels(bytes.size() / 4);
  if (!labels.empty()) std::memcpy(labels.data(), bytes.data(), bytes.size());
  return labels;
}

Scan read_scan(const fs::path& bin_path, const std::optional<fs::path>& label_path) {
  return read_points(bin_path, PointFormat::Kitti, label_path);
}

void write_bin(const fs::path& path, const std::vector<Point>& points) {
  write_file_atomic(path, points.data(), points.size() * sizeof(Point));
}

void write_labels(const fs::path& path, const std::vector<uint32_t>& labels) {
  write_file_atomic(path, labels.data(), labels.size() * sizeof(uint32_t));
}

std::vector<Pose> read_poses(const fs::path& path) {
  const std::string text = read_file_text(path);
  std::vector<Pose> poses;
  std::vector<double> values;
  const auto lines = split_lines(text);
  for (size_t i = 0; i < lines.size(); ++i) {
    if (blank(lines[i])) continue;
    PS_CHECK(parse_numbers(lines[i], values), "{}:{}: pose line has a token that is not a finite number",
             path.string(), i + 1);
    PS_CHECK(values.size() == 12, "{}:{}: pose line has {} numbers, expected 12 (row-major 3x4)", path.string(), i + 1,
             values.size());
    poses.push_back(pose_from_12(values));
  }
  return poses;
}

void write_poses(const fs::path& path, const std::vector<Pose>& poses) {
  write_file_atomic(path, [&](std::ostream& out) {
    for (const Pose& p : poses) {
      write_12(out, p.topRows<3>());
      out << '\n';
    }
  });
}

Calib read_calib(const fs::path& path) {
  const std::string text = read_file_text(path);
  Calib calib;
  bool have_tr = false;
  std::vector<double> values;
  const auto lines = split_lines(text);
  for (size_t i = 0; i < lines.size(); ++i) {
    std::string_view line = lines[i];
    if (blank(line)) continue;
    const size_t colon = line.find(':');
    PS_CHECK(colon != std::string_view::npos, "{}:{}: expected 'KEY: 12 numbers'", path.string(), i + 1);
    std::string_view key = line.substr(0, colon);
    while (!key.empty() && std::isspace(static_cast<unsigned char>(key.front()))) key.remove_prefix(1);
    PS_CHECK(parse_numbers(line.substr(colon + 1), values), "{}:{}: {} has a token that is not a finite number",
             path.string(), i + 1, key);
    PS_CHECK(values.size() == 12, "{}:{}: {} has {} numbers, expected 12", path.string(), i + 1, key, values.size());
    const Pose m = pose_from_12(values);
    if (key == "Tr") {
      calib.Tr = m;
      have_tr = true;
    } else if (key.size() == 2 && key[0] == 'P' && key[1] >= '0' && key[1] <= '3') {
      calib.P[static_cast<size_t>(key[1] - '0')] = m.topRows<3>();
    }
  }
  PS_CHECK(have_tr, "{}: no 'Tr:' line (the LiDAR -> cam0 transform)", path.string());
  PS_CHECK(std::abs(calib.Tr.topLeftCorner<3, 3>().determinant()) > 1e-9, "{}: Tr is singular", path.string());
  return calib;
}

void write_calib(const fs::path& path, const Calib& calib) {
  write_file_atomic(path, [&](std::ostream& out) {
    for (int i = 0; i < 4; ++i) {
      out << 'P' << i << ": ";
      write_12(out, calib.P[static_cast<size_t>(i)]);
      out << '\n';
    }
    out << "Tr: ";
    write_12(out, calib.Tr.topRows<3>());
    out << '\n';
  });
}

std::vector<Pose> lidar_poses(const std::vector<Pose>& cam0_poses, const Calib& calib) {
  const Pose tr_inv = calib.Tr.inverse();
  std::vector<Pose> out;
  out.reserve(cam0_poses.size());
  for (const Pose& p : cam0_poses) out.push_back(tr_inv * p * calib.Tr);
  return out;
}

std::string sequence_name(int id) { return fmt::format("{:02}", id); }

Sequence::Sequence(const fs::path& root, int id, const InputMapping& input)
    : dir_(root / "sequences" / sequence_name(id)), id_(id), input_(input) {
  const fs::path velodyne = dir_ / "velodyne";
  PS_CHECK(fs::is_directory(velodyne), "{}: no such directory (expected ROOT/sequences/{}/velodyne)", velodyne.string(),
           sequence_name(id));
  std::vector<std::pair<int, fs::path>> found;
  for (const auto& entry : fs::directory_iterator(velodyne)) {
    const std::string_view suffix = point_file_suffix(entry.path());
    if (suffix.empty()) continue;
    const std::string name = entry.path().filename().string();
    const std::string_view stem = std::string_view(name).substr(0, name.size() - suffix.size());
    int frame = -1;
    const auto [ptr, ec] = std::from_chars(stem.data(), stem.data() + stem.size(), frame);
    if (ec != std::errc() || ptr != stem.data() + stem.size() || frame < 0) {
      spdlog::warn("{}: ignoring file not named NNNNNN.bin (or .pcd, .ply, .npy, .pcd.bin)", entry.path().string());
      continue;
    }
    found.emplace_back(frame, entry.path());
  }
  std::sort(found.begin(), found.end());
  for (size_t k = 0; k < found.size(); ++k) {
    PS_CHECK(k == 0 || found[k].first != found[k - 1].first, "{}: two point files of scan {:06}: {} and {}",
             velodyne.string(), found[k].first, found[k - 1].second.filename().string(),
             found[k].second.filename().string());
    frames_.push_back(found[k].first);
    scan_paths_.push_back(found[k].second);
  }
  check_transform(input_.transform, dir_.string() + ": the input mapping");
  const fs::path poses_file = dir_ / "poses.txt", calib_file = dir_ / "calib.txt";
  if (fs::exists(poses_file) && fs::exists(calib_file)) {
    const auto cam0 = read_poses(poses_file);
    const Calib calib = read_calib(calib_file);
    // poses.txt has one line per scan of the sequence, frame numbers are line numbers.
    const int last = frames_.empty() ? -1 : frames_.back();
    PS_CHECK(static_cast<int>(cam0.size()) > last, "{}: {} poses, but the sequence has scan {:06}",
             poses_file.string(), cam0.size(), last);
    // In the model's frame (points p' = M p) scan i's pose is T_i M^-1, so that relative(i, j)
    // = M T_i^-1 T_j M^-1 moves mapped points as the original ones moved.
    const Pose to_sensor = input_.transform.inverse();
    const auto all = lidar_poses(cam0, calib);
    for (int f : frames_) poses_.push_back(all[static_cast<size_t>(f)] * to_sensor);
  }
}

const fs::path& Sequence::scan_path(size_t i) const { return scan_paths_.at(i); }
fs::path Sequence::label_path(size_t i) const { return dir_ / "labels" / fmt::format("{:06}.label", frame(i)); }
bool Sequence::has_labels(size_t i) const { return fs::exists(label_path(i)); }

const Pose& Sequence::pose(size_t i) const {
  PS_CHECK(has_poses(), "{}: poses.txt and calib.txt are needed (dense ground truth uses the scan poses)",
           dir_.string());
  return poses_.at(i);
}

Pose Sequence::relative(size_t i, size_t j) const { return pose(i).inverse() * pose(j); }

Scan Sequence::load(size_t i) const {
  Scan scan = has_labels(i) ? read_points(scan_path(i), PointFormat::FromExtension, label_path(i))
                            : read_points(scan_path(i));
  input_.apply(scan.points);
  return scan;
}

std::vector<int> list_sequences(const fs::path& root) {
  const fs::path dir = root / "sequences";
  PS_CHECK(fs::is_directory(dir), "{}: no such directory (expected a SemanticKITTI ROOT with sequences/)",
           dir.string());
  std::vector<int> ids;
  for (const auto& entry : fs::directory_iterator(dir)) {
    const std::string name = entry.path().filename().string();
    int id = -1;
    const auto [ptr, ec] = std::from_chars(name.data(), name.data() + name.size(), id);
    if (entry.is_directory() && ec == std::errc() && ptr == name.data() + name.size() && name.size() == 2)
      ids.push_back(id);
  }
  std::sort(ids.begin(), ids.end());
  return ids;
}

std::vector<int> split_sequences(const std::string& split) {
  if (split == "train") return {0, 1, 2, 3, 4, 5, 6, 7, 9, 10};
  if (split == "val" || split == "valid" || split == "validation") return {8};
  PS_FAIL("unknown split '{}': expected train or val", split);
}

}  // namespace pillarseg
