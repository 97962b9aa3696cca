// Portable pseudo-random numbers for the simulated devices.
// xoshiro256** (Blackman & Vigna 2018, https://prng.di.unimi.it/) seeded through splitmix64, and a
// Marsaglia polar Gaussian. The integer and uniform streams are bit-identical on every platform
// (pure 64-bit integer arithmetic); the Gaussian transform uses only std::log and std::sqrt (sqrt
// is exact IEEE; log is correctly rounded in glibc and newlib for these arguments in practice).
// Unlike std::normal_distribution, whose algorithm is implementation-defined, the sequence does not
// depend on the standard library. Heap-free, noexcept, no exceptions: usable in a bare-metal image.
#pragma once

#include <cmath>
#include <cstdint>

namespace magvec::drivers::sim {

// splitmix64: a 64-bit counter-based mixer; used to seed xoshiro and for random-access draws.
class SplitMix64 {
 public:
  explicit constexpr SplitMix64(std::uint64_t seed) noexcept : state_(seed) {}
  constexpr std::uint64_t next() noexcept {
    std::uint64_t z = (state_ += 0x9E3779B97F4A7C15ULL);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
  }
  // Uniform in [0, 1) with 53 random bits.
  constexpr double uniform() noexcept { return static_cast<double>(next() >> 11) * 0x1.0p-53; }

 private:
  std::uint64_t state_;
};

class Xoshiro256 {
 public:
  explicit constexpr Xoshiro256(std::uint64_t seed) noexcept : s_{} {
    SplitMix64 sm(seed);
    for (std::uint64_t& w : s_)
      w = sm.next();
  }
  constexpr std::uint64_t next() noexcept {
    const std::uint64_t result = rotl(s_[1] * 5U, 7) * 9U;
    const std::uint64_t t = s_[1] << 17;
    s_[2] ^= s_[0];
    s_[3] ^= s_[1];
    s_[1] ^= s_[2];
    s_[0] ^= s_[3];
    s_[2] ^= t;
    s_[3] = rotl(s_[3], 45);
    return result;
  }
  // Uniform in [0, 1) with 53 random bits.
  constexpr double uniform() noexcept { return static_cast<double>(next() >> 11) * 0x1.0p-53; }

 private:
  static constexpr std::uint64_t rotl(std::uint64_t x, int k) noexcept {
    return (x << k) | (x >> (64 - k));
  }
  std::uint64_t s_[4];
};

// Standard normal variates by Marsaglia's polar method (two per accepted pair; the spare is kept).
class Gaussian {
 public:
  explicit constexpr Gaussian(std::uint64_t seed) noexcept : rng_(seed) {}
  double next() noexcept {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    double u = 0.0, v = 0.0, s = 0.0;
    do {
      u = 2.0 * rng_.uniform() - 1.0;
      v = 2.0 * rng_.uniform() - 1.0;
      s = u * u + v * v;
    } while (s >= 1.0 || s == 0.0);
    const double f = std::sqrt(-2.0 * std::log(s) / s);
    spare_ = v * f;
    has_spare_ = true;
    return u * f;
  }
  Xoshiro256& uniform_source() noexcept { return rng_; }

 private:
  Xoshiro256 rng_;
  double spare_ = 0.0;
  bool has_spare_ = false;
};

// The seed of a simulated device's fault stream: the device's seed mixed with the stream's
// identifier, so that enabling one fault never moves the draws of another.
constexpr std::uint64_t device_stream_seed(std::uint64_t seed, std::uint64_t stream) noexcept {
  SplitMix64 sm(seed ^ (stream * 0x9E3779B97F4A7C15ULL));
  return sm.next();
}

// True with probability p (one draw, also when it comes out false; never a draw for p <= 0).
inline bool draw(Xoshiro256& rng, double p) noexcept {
  return p > 0 && rng.uniform() < p;
}

// Uniform integer in [0, n) (0 for n = 0).
constexpr std::uint64_t below(Xoshiro256& rng, std::uint64_t n) noexcept {
  return n == 0 ? 0 : rng.next() % n;
}

}  // namespace magvec::drivers::sim
