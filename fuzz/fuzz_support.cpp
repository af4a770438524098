#include "fuzz/fuzz_support.hpp"

#include <fmt/format.h>
#include <spdlog/spdlog.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>

#include "core/io.hpp"
#include "engine/backend/backend.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/model/run_config.hpp"

namespace pillarseg::fuzz {

namespace fs = std::filesystem;

namespace {

[[noreturn]] void harness_failure(const std::string& message) {
  std::fprintf(stderr, "fuzz harness: %s\n", message.c_str());
  std::abort();
}

fs::path make_scratch_dir() {
  const char* tmp = std::getenv("TMPDIR");
  const fs::path dir =
      fs::path(tmp && *tmp ? tmp : "/tmp") / fmt::format("pillarseg-fuzz-{}", ::getpid());
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) harness_failure(fmt::format("cannot create {}: {}", dir.string(), ec.message()));
  return dir;
}

void remove_scratch_dir() {
  std::error_code ec;
  fs::remove_all(scratch_dir(), ec);
}

}  // namespace

void quiet_logs() {
  spdlog::set_level(spdlog::level::off);
}

const fs::path& scratch_dir() {
  static const fs::path dir = make_scratch_dir();
  // Registered after dir is constructed, so it runs before dir is destroyed.
  static const bool removed_at_exit = std::atexit(remove_scratch_dir) == 0;
  static_cast<void>(removed_at_exit);
  return dir;
}

void write_file(const fs::path& path, const uint8_t* data, size_t size) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  if (!out) harness_failure(fmt::format("cannot write {}", path.string()));
}

void write_file(const fs::path& path, std::string_view text) {
  write_file(path, reinterpret_cast<const uint8_t*>(text.data()), text.size());
}

fs::path write_scratch(std::string_view name, const uint8_t* data, size_t size) {
  fs::path path = scratch_dir() / name;
  write_file(path, data, size);
  return path;
}

const std::string& tiny_model_config() {
  static const std::string text = read_file_text(fs::path(PILLARSEG_FUZZ_DIR) / "tiny_model.yaml");
  return text;
}

const fs::path& tiny_checkpoint() {
  static const fs::path path = [] {
    const fs::path file = scratch_dir() / "tiny.safetensors";
    const RunConfig config = parse_run_config(tiny_model_config(), "fuzz/tiny_model.yaml");
    auto backend = make_cpu_backend();
    PillarSegNet net(config.model, *backend, /*seed=*/11);
    save_checkpoint(file, net, config, {}, /*with_optimizer=*/false);
    return file;
  }();
  return path;
}

void check(bool condition, std::string_view what) {
  if (!condition) harness_failure(fmt::format("invariant violated: {}", what));
}

void check_scan(const Scan& scan) {
  check(scan.labels.empty(), "no labels without a .label file");
  for (const Point& p : scan.points)
    check(std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z) && std::isfinite(p.r),
          "kept points are finite");
}

void check_c_api_error(const char* function, const char* error) {
  const std::string_view message(error);
  if (message.find(": unexpected error") != std::string_view::npos ||
      message.find(": out of memory") != std::string_view::npos)
    harness_failure(fmt::format("{} failed with an error that is not a pillarseg::Error: {}",
                                function, message));
}

}  // namespace pillarseg::fuzz
