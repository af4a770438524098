// Rng: xoshiro256** seeded through splitmix64. Our own distributions (not <random>'s, whose
// output differs between standard libraries) so that the same seed gives the same run
// everywhere. Streams for independent work (one per sample, per epoch) come from
// Rng::derive(seed, a, b), so results do not depend on thread scheduling.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <numbers>

namespace pillarseg {

class Rng {
  __extension__ typedef unsigned __int128 uint128;

 public:
  using State = std::array<uint64_t, 4>;

  explicit Rng(uint64_t seed = 0) { reseed(seed); }

  static Rng derive(uint64_t seed, uint64_t a, uint64_t b = 0) {
    uint64_t s = seed;
    uint64_t h = splitmix(s) ^ (a * 0x9E3779B97F4A7C15ull);
    h = splitmix(h) ^ (b * 0xC2B2AE3D27D4EB4Full);
    return Rng(splitmix(h));
  }

  void reseed(uint64_t seed) {
    uint64_t s = seed;
    for (auto& w : state_) w = splitmix(s);
  }

  uint64_t next_u64() {
    const uint64_t result = rotl(state_[1] * 5, 7) * 9;
    const uint64_t t = state_[1] << 17;
    state_[2] ^= state_[0];
    state_[3] ^= state_[1];
    state_[1] ^= state_[2];
    state_[0] ^= state_[3];
    state_[2] ^= t;
    state_[3] = rotl(state_[3], 45);
    return result;
  }

  // Uniform in [0, 1) with 53 random bits.
  double uniform() { return static_cast<double>(next_u64() >> 11) * 0x1.0p-53; }
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  // Uniform integer in [0, n), unbiased (Lemire's method with rejection).
  uint64_t uniform_int(uint64_t n) {
    if (n == 0) return 0;
    while (true) {
      const uint128 m = static_cast<uint128>(next_u64()) * n;
      const uint64_t low = static_cast<uint64_t>(m);
      if (low >= n || low >= (-n) % n) return static_cast<uint64_t>(m >> 64);
    }
  }
  bool bernoulli(double p) { return uniform() < p; }
  // Standard normal by Box-Muller (one value per call; no cached second value, so the state
  // is the four words only).
  double normal() {
    double u1 = uniform();
    while (u1 <= 0.0) u1 = uniform();
    const double u2 = uniform();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);
  }
  double normal(double mean, double sigma) { return mean + sigma * normal(); }

  // Fisher-Yates shuffle of [first, last).
  template <class It>
  void shuffle(It first, It last) {
    const auto n = last - first;
    for (auto i = n - 1; i > 0; --i) {
      const auto j = static_cast<decltype(i)>(uniform_int(static_cast<uint64_t>(i) + 1));
      std::swap(first[i], first[j]);
    }
  }

  const State& state() const { return state_; }
  void set_state(const State& s) { state_ = s; }

 private:
  static uint64_t rotl(uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
  static uint64_t splitmix(uint64_t& x) {
    uint64_t z = (x += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  State state_{};
};

}  // namespace pillarseg
