#include "core/fault.hpp"

#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <charconv>
#include <cstdio>
#include <cstdlib>
#include <string>

namespace pillarseg {

namespace {

struct FaultPlan {
  bool armed = false;
  std::string point;
  long long hit = 0;  // which arrival kills
  bool stop = false;  // PILLARSEG_FAULT_STOP=1: SIGSTOP instead of SIGKILL
};

long long parse_count(std::string_view text) {
  long long value = 0;
  const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  return ec == std::errc() && ptr == text.data() + text.size() ? value : -1;
}

// This process's MPI rank as the launcher exports it, -1 outside one.
long long launcher_rank() {
  for (const char* name : {"OMPI_COMM_WORLD_RANK", "PMI_RANK", "PMIX_RANK"}) {
    if (const char* value = std::getenv(name)) return parse_count(value);
  }
  return -1;
}

const FaultPlan& plan() {
  static const FaultPlan p = [] {
    FaultPlan out;
    const char* env = std::getenv("PILLARSEG_FAULT");
    if (env == nullptr || *env == '\0') return out;
    std::string_view spec(env);
    long long rank = -1;
    if (const size_t at = spec.rfind('@'); at != std::string_view::npos) {
      rank = parse_count(spec.substr(at + 1));
      spec = spec.substr(0, at);
    }
    const size_t colon = spec.rfind(':');
    const long long hit = colon == std::string_view::npos ? -1 : parse_count(spec.substr(colon + 1));
    if (hit < 1) {
      std::fprintf(stderr, "PILLARSEG_FAULT='%s': expected POINT:N[@RANK] with N >= 1\n", env);
      std::exit(2);
    }
    if (rank >= 0 && rank != launcher_rank()) return out;
    out.armed = true;
    out.point = std::string(spec.substr(0, colon));
    out.hit = hit;
    const char* stop = std::getenv("PILLARSEG_FAULT_STOP");
    out.stop = stop != nullptr && std::string_view(stop) == "1";
    return out;
  }();
  return p;
}

}  // namespace

void fault_point(std::string_view point) {
  static std::atomic<long long> arrivals{0};
  const FaultPlan& p = plan();
  if (!p.armed) return;
  const bool matches = p.point.ends_with('*')
                           ? point.starts_with(std::string_view(p.point).substr(0, p.point.size() - 1))
                           : point == p.point;
  if (!matches) return;
  if (arrivals.fetch_add(1) + 1 == p.hit) {
    std::fprintf(stderr, "PILLARSEG_FAULT: %s process %d at %s (arrival %lld)\n",
                 p.stop ? "stopping" : "killing", ::getpid(), p.point.c_str(), p.hit);
    ::kill(::getpid(), p.stop ? SIGSTOP : SIGKILL);
  }
}

}  // namespace pillarseg
