// pillarseg info: what a SemanticKITTI root holds (sequences, scans, labels, poses) and, for
// one scan, its point count, range, in-grid count and class histogram.
#include <fmt/format.h>

#include <filesystem>

#include "core/classes.hpp"
#include "core/error.hpp"
#include "core/grid.hpp"
#include "engine/cli/commands.hpp"
#include "engine/data/class_table_yaml.hpp"
#include "engine/data/semantickitti.hpp"

namespace pillarseg::cli {

namespace {

struct InfoArgs {
  std::string data;
  int sequence = -1;
  int scan = -1;
  std::string classes;
};

void print_root(const std::filesystem::path& root) {
  const auto ids = list_sequences(root);
  fmt::print("{}: {} sequence(s)\n", root.string(), ids.size());
  fmt::print("{:>4} {:>7} {:>7} {:>6}\n", "seq", "scans", "labels", "poses");
  for (int id : ids) {
    const Sequence seq(root, id);
    size_t labelled = 0;
    for (size_t i = 0; i < seq.size(); ++i) labelled += seq.has_labels(i);
    fmt::print("{:>4} {:>7} {:>7} {:>6}\n", sequence_name(id), seq.size(), labelled, seq.has_poses() ? "yes" : "no");
  }
}

void print_scan(const Sequence& seq, size_t index, const ClassTable& classes) {
  const Scan scan = seq.load(index);
  const GridSpec grid;
  int64_t in_grid = 0, moving = 0;
  float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  std::array<int64_t, kNumClassIds> hist{};
  for (size_t i = 0; i < scan.points.size(); ++i) {
    const Point& p = scan.points[i];
    const float v[3] = {p.x, p.y, p.z};
    for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], v[a]), hi[a] = std::max(hi[a], v[a]);
    in_grid += grid.contains(p.x, p.y, p.z);
    if (!scan.labels.empty()) {
      hist[classes.class_of(scan.labels[i])]++;
      moving += classes.is_moving(scan.labels[i]);
    }
  }
  fmt::print("{}\n", seq.scan_path(index).string());
  fmt::print("points: {} ({} dropped as non-finite), {} inside the default grid\n", scan.points.size(),
             scan.dropped_nonfinite, in_grid);
  if (!scan.points.empty())
    fmt::print("extent: x [{:.2f}, {:.2f}]  y [{:.2f}, {:.2f}]  z [{:.2f}, {:.2f}] m\n", lo[0], hi[0], lo[1], hi[1],
               lo[2], hi[2]);
  if (scan.labels.empty()) {
    fmt::print("labels: none\n");
    return;
  }
  fmt::print("labels: {} moving points (raw ids 252-259)\n", moving);
  fmt::print("{:>3} {:<13} {:>8} {:>7}\n", "id", "class", "points", "share");
  for (int c = 0; c < kNumClassIds; ++c)
    fmt::print("{:>3} {:<13} {:>8} {:>6.2f}%\n", c, classes.name(c), hist[c],
               scan.points.empty() ? 0.0 : 100.0 * static_cast<double>(hist[c]) / static_cast<double>(scan.points.size()));
}

void run_info(const InfoArgs& args) {
  const std::filesystem::path root(args.data);
  const ClassTable classes = args.classes.empty() ? ClassTable::defaults() : load_class_table(args.classes);
  if (args.sequence < 0) {
    PS_CHECK(args.scan < 0, "--scan needs --sequence");
    print_root(root);
    return;
  }
  const Sequence seq(root, args.sequence);
  if (args.scan < 0) {
    fmt::print("sequence {}: {} scans, poses {}\n", sequence_name(seq.id()), seq.size(), seq.has_poses() ? "yes" : "no");
    if (seq.size()) fmt::print("frames {:06} .. {:06}\n", seq.frame(0), seq.frame(seq.size() - 1));
    return;
  }
  size_t index = seq.size();
  for (size_t i = 0; i < seq.size(); ++i)
    if (seq.frame(i) == args.scan) index = i;
  PS_CHECK(index < seq.size(), "--scan {}: no point file {:06}.* in {}", args.scan, args.scan,
           (seq.dir() / "velodyne").string());
  print_scan(seq, index, classes);
}

}  // namespace

void add_info(CLI::App& app) {
  auto args = std::make_shared<InfoArgs>();
  CLI::App* cmd = app.add_subcommand("info", "What a data set holds; one scan's points and class histogram");
  cmd->add_option("--data", args->data, "SemanticKITTI root (holds sequences/)")->required();
  cmd->add_option("--sequence", args->sequence, "sequence number, e.g. 8 or 08");
  cmd->add_option("--scan", args->scan, "scan (frame) number within the sequence");
  cmd->add_option("--classes", args->classes, "class table YAML overriding the default mapping");
  cmd->callback([args] { run_info(*args); });
}

}  // namespace pillarseg::cli
